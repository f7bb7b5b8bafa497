//! The ISO 230-2 part program for the CNC, generated from a `Plan` in one of four dialects.
//!
//! - ISO / Fanuc: `G01 X.. F..`, dwell `G04 P<ms>` (Fanuc's P is milliseconds), `M30`, `%`.
//! - Siemens (Sinumerik): `N..` blocks, dwell `G4 F<s>`, `; comments`, `M30`.
//! - Heidenhain conversational: `BEGIN PGM`, `L X+.. F..`, dwell cycle `CYCL DEF 9.0/9.1`,
//!   `END PGM`, numbered lines.
//! - LinuxCNC (rs274ngc): `G1 X.. F..`, dwell `G4 P<s>` (LinuxCNC's P is seconds), `M2`.
//!
//! Capture is by stability (the program only dwells) or by handshake with the PLC: at each
//! target the program outputs the target's code and raises "at target", then waits for
//! "captured". The handshake lines are emitted for the ISO/Fanuc dialect (custom macro B: an
//! output variable and a WHILE wait on an input variable) and for LinuxCNC (M68 analog output,
//! M64/M65 digital output, M66 wait on a digital input); which signals are used is the site's
//! choice (`Handshake`). Siemens and Heidenhain programs dwell only.

use super::Direction;
use super::plan::{Plan, Step};
use std::fmt::Write as _;
use thiserror::Error;

/// CNC program dialect.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Dialect {
    Iso,
    Siemens,
    Heidenhain,
    LinuxCnc,
}

impl Dialect {
    /// Parse a dialect name: iso (or fanuc), siemens, heidenhain, linuxcnc.
    pub fn parse(s: &str) -> Option<Dialect> {
        Some(match s.to_ascii_lowercase().as_str() {
            "iso" | "fanuc" => Dialect::Iso,
            "siemens" | "sinumerik" => Dialect::Siemens,
            "heidenhain" => Dialect::Heidenhain,
            "linuxcnc" => Dialect::LinuxCnc,
            _ => return None,
        })
    }

    /// The name [`Dialect::parse`] reads.
    pub fn name(self) -> &'static str {
        match self {
            Dialect::Iso => "iso",
            Dialect::Siemens => "siemens",
            Dialect::Heidenhain => "heidenhain",
            Dialect::LinuxCnc => "linuxcnc",
        }
    }

    /// The usual file extension.
    pub fn extension(self) -> &'static str {
        match self {
            Dialect::Iso => "nc",
            Dialect::Siemens => "mpf",
            Dialect::Heidenhain => "h",
            Dialect::LinuxCnc => "ngc",
        }
    }
}

/// The PLC signals of the handshake (site's choice).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Handshake {
    /// Output carrying the target code (Fanuc: a macro output variable such as #1132 for
    /// UO000–UO031; LinuxCNC: analog output number for M68 E).
    pub code_output: u32,
    /// Digital output "at target" (Fanuc: output variable such as #1100; LinuxCNC: M64 P).
    pub at_target_output: u32,
    /// Digital input "captured" (Fanuc: input variable such as #1000; LinuxCNC: M66 P).
    pub captured_input: u32,
    /// Longest wait for "captured" (s); LinuxCNC aborts the wait after it.
    pub timeout_s: f64,
}

impl Default for Handshake {
    fn default() -> Self {
        Handshake {
            code_output: 0,
            at_target_output: 0,
            captured_input: 0,
            timeout_s: 30.0,
        }
    }
}

/// How targets are captured.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum CaptureMode {
    /// The program dwells; the service captures when the spot is at rest.
    Stability,
    /// The program tells the PLC it is at target k and waits for "captured".
    Handshake(Handshake),
}

/// Why a program could not be generated.
#[derive(Clone, Debug, Error, PartialEq)]
pub enum ProgramError {
    #[error(
        "the {} dialect has no handshake here: use stability capture (dwell) or the ISO/Fanuc or LinuxCNC dialect", .0.name()
    )]
    NoHandshake(Dialect),
}

/// The code sent for a target: `run·1000 + target_index·2 + (0 up, 1 down)`; the PLC echoes it.
pub fn target_code(run: u32, target_index: u32, direction: Direction) -> u32 {
    run * 1000 + target_index * 2 + u32::from(direction == Direction::Down)
}

/// Decode a target code.
pub fn decode_target_code(code: u32) -> (u32, u32, Direction) {
    let run = code / 1000;
    let rest = code % 1000;
    let dir = if rest % 2 == 1 {
        Direction::Down
    } else {
        Direction::Up
    };
    (run, rest / 2, dir)
}

/// Generate the program text for the whole cycle.
pub fn generate(plan: &Plan, dialect: Dialect, mode: CaptureMode) -> Result<String, ProgramError> {
    generate_steps(plan, &plan.steps(), "", dialect, mode)
}

/// The rest of the cycle after the captures in `done`: from the stop before the first missing
/// capture (so it is approached from the right side) to the end. `None` when nothing is
/// missing.
pub fn remaining_steps(
    plan: &Plan,
    done: &std::collections::BTreeSet<super::TargetKey>,
) -> Option<Vec<Step>> {
    let steps = plan.steps();
    let first = steps
        .iter()
        .position(|s| s.target.is_some_and(|k| !done.contains(&k)))?;
    let mut rest = steps[first.saturating_sub(1)..].to_vec();
    if first > 0 {
        // The stop before is only an approach point: no dwell, no capture there.
        rest[0].target = None;
    }
    Some(rest)
}

/// A make-up pass over `missing` captures, as one sweep: the upward ones by increasing
/// position, then the downward ones by decreasing position, each approached from its
/// direction's side from `approach_mm` before it. In the cycle's order the carriage would
/// cross the travel between most of them, and every crossing is a follower step whose
/// settling eats the dwell the capture needs.
pub fn makeup_steps(plan: &Plan, missing: &[super::TargetKey], approach_mm: f64) -> Vec<Step> {
    let mut keys: Vec<(f64, super::TargetKey)> = missing
        .iter()
        .filter_map(|k| Some((*plan.targets.get(k.target_index as usize)?, *k)))
        .collect();
    keys.sort_by(|(a, ka), (b, kb)| match (ka.direction, kb.direction) {
        (Direction::Up, Direction::Down) => std::cmp::Ordering::Less,
        (Direction::Down, Direction::Up) => std::cmp::Ordering::Greater,
        (Direction::Up, Direction::Up) => a.total_cmp(b).then(ka.run.cmp(&kb.run)),
        (Direction::Down, Direction::Down) => b.total_cmp(a).then(ka.run.cmp(&kb.run)),
    });
    let mut out = Vec::with_capacity(2 * keys.len());
    for (t, k) in keys {
        let from = match k.direction {
            Direction::Up => t - approach_mm,
            Direction::Down => t + approach_mm,
        };
        out.push(Step {
            position_mm: from,
            target: None,
        });
        out.push(Step {
            position_mm: t,
            target: Some(k),
        });
    }
    out
}

/// Generate the program text for `steps` of `plan`; `note` is added to the title.
pub fn generate_steps(
    plan: &Plan,
    steps: &[Step],
    note: &str,
    dialect: Dialect,
    mode: CaptureMode,
) -> Result<String, ProgramError> {
    generate_settled(plan, steps, note, dialect, mode, 0.0)
}

/// Generate the program text for `steps` of `plan`, holding each approach point (a stop that
/// is no capture) for `approach_dwell_s` seconds. A resumed or make-up program reaches its
/// approach points from anywhere on the axis: after a long move the follower is still
/// settling, PSD2 may not see the spot at the approach point at all, and the capture that
/// follows could not tell which side the carriage came from. Held there, it can.
pub fn generate_settled(
    plan: &Plan,
    steps: &[Step],
    note: &str,
    dialect: Dialect,
    mode: CaptureMode,
    approach_dwell_s: f64,
) -> Result<String, ProgramError> {
    if matches!(mode, CaptureMode::Handshake(_))
        && matches!(dialect, Dialect::Siemens | Dialect::Heidenhain)
    {
        return Err(ProgramError::NoHandshake(dialect));
    }
    let s = &plan.spec;
    let ax = s.axis.as_str();
    let title = format!(
        "axiscomp ISO 230-2 {ax} {:.3} to {:.3} mm, {} targets, {} runs, dwell {} s{}",
        s.start_mm,
        s.end_mm,
        plan.targets.len(),
        s.runs,
        s.dwell_s,
        if note.is_empty() {
            String::new()
        } else {
            format!(", {note}")
        }
    );
    let mut out = String::new();
    let mut w = Writer {
        dialect,
        out: &mut out,
        n: 0,
    };
    w.header(&title);
    let mut last_run = 0;
    for step in steps {
        if let Some(k) = step.target
            && k.run != last_run
        {
            last_run = k.run;
            w.comment(&format!("run {}", k.run));
        }
        w.move_to(ax, step, s.feed_mm_min);
        if step.target.is_none() && approach_dwell_s > 0.0 {
            w.dwell(approach_dwell_s);
        }
        if let Some(k) = step.target {
            match mode {
                CaptureMode::Stability => w.dwell(s.dwell_s),
                CaptureMode::Handshake(h) => {
                    w.dwell(s.dwell_s);
                    w.handshake(&h, target_code(k.run, k.target_index, k.direction));
                }
            }
        }
    }
    w.footer();
    Ok(out)
}

/// A program that visits `stops` in order on `axis` at `feed_mm_min`, dwelling `dwell_s` at
/// each: the follower's stop-and-go self-calibration (`follower::selfcal`), whose stops are
/// follower handovers, not captures. A stop's comment, when it has one, goes before it.
pub fn generate_stops(
    axis: &str,
    stops: &[(f64, Option<String>)],
    feed_mm_min: f64,
    dwell_s: f64,
    title: &str,
    dialect: Dialect,
) -> String {
    let mut out = String::new();
    let mut w = Writer {
        dialect,
        out: &mut out,
        n: 0,
    };
    w.header(title);
    for (x, comment) in stops {
        if let Some(c) = comment {
            w.comment(c);
        }
        w.move_to(
            axis,
            &Step {
                position_mm: *x,
                target: None,
            },
            feed_mm_min,
        );
        w.dwell(dwell_s);
    }
    w.footer();
    out
}

struct Writer<'a> {
    dialect: Dialect,
    out: &'a mut String,
    n: u32,
}

impl Writer<'_> {
    fn line(&mut self, text: &str) {
        match self.dialect {
            Dialect::Siemens => {
                self.n += 10;
                let _ = writeln!(self.out, "N{} {text}", self.n);
            }
            Dialect::Heidenhain => {
                let _ = writeln!(self.out, "{} {text}", self.n);
                self.n += 1;
            }
            _ => {
                let _ = writeln!(self.out, "{text}");
            }
        }
    }

    fn comment(&mut self, text: &str) {
        match self.dialect {
            // Fanuc comments are upper case without parentheses inside.
            Dialect::Iso => self.line(&format!(
                "({})",
                text.to_uppercase().replace(['(', ')'], "")
            )),
            Dialect::LinuxCnc => self.line(&format!("({})", text.replace(['(', ')'], ""))),
            Dialect::Siemens | Dialect::Heidenhain => self.line(&format!("; {text}")),
        }
    }

    fn header(&mut self, title: &str) {
        match self.dialect {
            Dialect::Iso => {
                let _ = writeln!(self.out, "%");
                self.line("O2302");
                self.comment(title);
                self.line("G21 G90 G94");
            }
            Dialect::Siemens => {
                self.comment(title);
                self.line("G90 G71 G94");
            }
            Dialect::Heidenhain => {
                self.line("BEGIN PGM AXISCOMP MM");
                self.comment(title);
            }
            Dialect::LinuxCnc => {
                self.comment(title);
                self.line("G21 G90 G94 G17");
            }
        }
    }

    fn move_to(&mut self, ax: &str, step: &Step, feed: f64) {
        let p = step.position_mm;
        match self.dialect {
            Dialect::Iso | Dialect::Siemens => self.line(&format!("G01 {ax}{p:.4} F{feed:.0}")),
            Dialect::LinuxCnc => self.line(&format!("G1 {ax}{p:.4} F{feed:.0}")),
            Dialect::Heidenhain => self.line(&format!("L {ax}{p:+.4} F{feed:.0}")),
        }
    }

    fn dwell(&mut self, secs: f64) {
        match self.dialect {
            Dialect::Iso => self.line(&format!("G04 P{:.0}", secs * 1000.0)),
            Dialect::Siemens => self.line(&format!("G4 F{secs:.3}")),
            Dialect::LinuxCnc => self.line(&format!("G4 P{secs:.3}")),
            Dialect::Heidenhain => {
                self.line("CYCL DEF 9.0 DWELL TIME");
                self.line(&format!("CYCL DEF 9.1 DWELL {secs:.3}"));
            }
        }
    }

    fn handshake(&mut self, h: &Handshake, code: u32) {
        match self.dialect {
            Dialect::Iso => {
                self.line(&format!("#{} = {code}", 1132 + h.code_output));
                self.line(&format!("#{} = 1", 1100 + h.at_target_output));
                self.line(&format!("WHILE [#{} EQ 0] DO1", 1000 + h.captured_input));
                self.line("END1");
                self.line(&format!("#{} = 0", 1100 + h.at_target_output));
            }
            Dialect::LinuxCnc => {
                self.line(&format!("M68 E{} Q{code}", h.code_output));
                self.line(&format!("M64 P{}", h.at_target_output));
                self.line(&format!("M66 P{} L3 Q{:.1}", h.captured_input, h.timeout_s));
                self.line(&format!("M65 P{}", h.at_target_output));
            }
            Dialect::Siemens | Dialect::Heidenhain => {}
        }
    }

    fn footer(&mut self) {
        match self.dialect {
            Dialect::Iso => {
                self.line("M30");
                let _ = writeln!(self.out, "%");
            }
            Dialect::Siemens => self.line("M30"),
            Dialect::Heidenhain => self.line("END PGM AXISCOMP MM"),
            Dialect::LinuxCnc => self.line("M2"),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::run::plan::PlanSpec;

    fn small_plan() -> Plan {
        Plan::new(PlanSpec {
            axis: "X".into(),
            start_mm: 0.0,
            end_mm: 100.0,
            targets: 5,
            runs: 2,
            overrun_mm: 2.0,
            dwell_s: 1.5,
            feed_mm_min: 1000.0,
            lead_mm: 0.0,
            reference_mm: None,
        })
        .unwrap()
    }

    #[test]
    fn dwell_units_differ_by_dialect() {
        let p = small_plan();
        let iso = generate(&p, Dialect::Iso, CaptureMode::Stability).unwrap();
        assert!(iso.contains("\nG04 P1500\n"), "Fanuc P is ms");
        assert!(iso.starts_with("%\nO2302\n") && iso.ends_with("M30\n%\n"));
        let cnc = generate(&p, Dialect::LinuxCnc, CaptureMode::Stability).unwrap();
        assert!(cnc.contains("\nG4 P1.500\n"), "LinuxCNC P is seconds");
        assert!(cnc.ends_with("M2\n"));
        let sie = generate(&p, Dialect::Siemens, CaptureMode::Stability).unwrap();
        assert!(sie.contains(" G4 F1.500\n") && sie.contains("N20 G90 G71 G94"));
        let hh = generate(&p, Dialect::Heidenhain, CaptureMode::Stability).unwrap();
        assert!(hh.starts_with("0 BEGIN PGM AXISCOMP MM\n"));
        assert!(hh.contains(" L X+25.0000 F1000\n") && hh.contains(" CYCL DEF 9.1 DWELL 1.500\n"));
        let last = hh.lines().last().unwrap();
        let n: usize = last.split(' ').next().unwrap().parse().unwrap();
        assert_eq!(n + 1, hh.lines().count(), "consecutive line numbers");
        assert!(last.ends_with("END PGM AXISCOMP MM"));
    }

    #[test]
    fn every_target_is_visited_with_a_dwell() {
        let p = small_plan();
        let cnc = generate(&p, Dialect::LinuxCnc, CaptureMode::Stability).unwrap();
        let moves = cnc.lines().filter(|l| l.starts_with("G1 X")).count();
        assert_eq!(moves, p.steps().len());
        let dwells = cnc.lines().filter(|l| l.starts_with("G4 P")).count();
        assert_eq!(dwells, p.capture_count());
    }

    #[test]
    fn remaining_and_makeup_steps() {
        let p = small_plan();
        let all: Vec<_> = p.steps().iter().filter_map(|s| s.target).collect();
        let done: std::collections::BTreeSet<_> = all[..3].iter().copied().collect();
        let rest = remaining_steps(&p, &done).unwrap();
        // Starts at the stop before the 4th capture, so it is approached from below.
        assert_eq!(rest[1].target, Some(all[3]));
        assert_eq!(rest[0].target, None, "the approach point is no capture");
        assert!(rest[0].position_mm < rest[1].position_mm);
        assert_eq!(
            rest.iter().filter(|s| s.target.is_some()).count(),
            all.len() - 3
        );
        let everything: std::collections::BTreeSet<_> = all.iter().copied().collect();
        assert!(remaining_steps(&p, &everything).is_none());
        let down = all
            .iter()
            .find(|k| k.direction == Direction::Down)
            .copied()
            .unwrap();
        let m = makeup_steps(&p, &[down], 2.0);
        assert_eq!(m.len(), 2);
        assert!(m[0].position_mm > m[1].position_mm, "approached from above");
        // Several: one sweep up, then one down, each stop approached from its side.
        let missing = [all[12], all[1], all[8], all[3], all[16], all[0]];
        let m = makeup_steps(&p, &missing, 2.0);
        let order: Vec<_> = m.iter().filter_map(|s| s.target).collect();
        let (ups, downs): (Vec<_>, Vec<_>) =
            order.iter().partition(|k| k.direction == Direction::Up);
        assert_eq!(order.len(), missing.len());
        assert_eq!(&order[..ups.len()], &ups[..], "the upward ones first");
        assert!(
            ups.windows(2)
                .all(|w| w[0].target_index <= w[1].target_index)
        );
        assert!(
            downs
                .windows(2)
                .all(|w| w[0].target_index >= w[1].target_index)
        );
        for pair in m.chunks(2) {
            let k = pair[1].target.unwrap();
            assert_eq!(pair[0].target, None);
            assert_eq!(
                pair[0].position_mm < pair[1].position_mm,
                k.direction == Direction::Up,
                "{k:?} approached from its side"
            );
        }
        let text =
            generate_steps(&p, &m, "make-up", Dialect::LinuxCnc, CaptureMode::Stability).unwrap();
        // Held at the approach points on request only.
        let dwells = |t: &str| t.lines().filter(|l| l.starts_with("G4 P")).count();
        assert_eq!(dwells(&text), 6);
        let held = generate_settled(
            &p,
            &m,
            "make-up",
            Dialect::LinuxCnc,
            CaptureMode::Stability,
            0.5,
        )
        .unwrap();
        assert_eq!(dwells(&held), 12);
        assert_eq!(held.matches("G4 P0.500").count(), 6);
        assert!(text.starts_with(
            "(axiscomp ISO 230-2 X 0.000 to 100.000 mm, 5 targets, 2 runs, dwell 1.5 s, make-up)"
        ));
    }

    #[test]
    fn a_stop_and_go_program_dwells_at_every_stop() {
        let stops = vec![
            (12.0, Some("lead-in".to_string())),
            (0.0, None),
            (3.75, Some("pass 1 (up)".to_string())),
        ];
        let cnc = generate_stops("X", &stops, 1000.0, 2.1, "follower map", Dialect::LinuxCnc);
        assert_eq!(
            cnc,
            "(follower map)\nG21 G90 G94 G17\n(lead-in)\nG1 X12.0000 F1000\nG4 P2.100\nG1 X0.0000 F1000\nG4 P2.100\n(pass 1 up)\nG1 X3.7500 F1000\nG4 P2.100\nM2\n"
        );
        let iso = generate_stops("Y", &stops, 1000.0, 2.1, "follower map", Dialect::Iso);
        assert_eq!(iso.matches("G04 P2100\n").count(), 3);
        assert!(iso.contains("(PASS 1 UP)\nG01 Y3.7500 F1000\n"), "{iso}");
        let hh = generate_stops("X", &stops, 1000.0, 2.1, "m", Dialect::Heidenhain);
        assert_eq!(hh.matches("CYCL DEF 9.1 DWELL 2.100").count(), 3);
        let sie = generate_stops("X", &stops, 1000.0, 2.1, "m", Dialect::Siemens);
        assert!(sie.contains(" G4 F2.100\n") && sie.ends_with(" M30\n"));
    }

    #[test]
    fn handshake_lines_and_codes() {
        let p = small_plan();
        let hs = CaptureMode::Handshake(Handshake::default());
        let cnc = generate(&p, Dialect::LinuxCnc, hs).unwrap();
        assert_eq!(cnc.matches("M66 P0 L3 Q30.0").count(), p.capture_count());
        assert!(cnc.contains("M68 E0 Q1000\n"), "run 1, target 0, up");
        assert!(cnc.contains("M68 E0 Q2009\n"), "run 2, target 4, down");
        let iso = generate(&p, Dialect::Iso, hs).unwrap();
        assert!(iso.contains("#1132 = 1000\n#1100 = 1\nWHILE [#1000 EQ 0] DO1\nEND1\n#1100 = 0\n"));
        assert_eq!(
            generate(&p, Dialect::Siemens, hs),
            Err(ProgramError::NoHandshake(Dialect::Siemens))
        );
        for run in 1..4 {
            for t in 0..41 {
                for d in [Direction::Up, Direction::Down] {
                    assert_eq!(decode_target_code(target_code(run, t, d)), (run, t, d));
                }
            }
        }
    }
}
