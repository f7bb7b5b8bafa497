//! The twin's CNC: parses the part program the service wrote (ISO/Fanuc and LinuxCNC
//! dialects, see `run::program`) and executes it against the plant: linear moves at the
//! programmed feed, dwells, and the PLC handshake (at target / wait for captured).
//! Sans-I/O: `step(now, ...)` advances it; it moves the carriage through the plant.
//!
//! Supported words: `G0`/`G1` with one axis word and `F` (mm/min, modal), `G4` (ISO: `P` in
//! ms or `X` in s; LinuxCNC: `P` in s), `G21 G90 G94 G17` (accepted), `M2`/`M30`; comments
//! in parentheses; `%` and `O…` lines. Handshake: LinuxCNC `M68 E… Q<code>`, `M64 P…`,
//! `M66 P… L3 Q<timeout>`, `M65 P…`; Fanuc macro `#1132 = <code>`, `#1100 = 1|0`,
//! `WHILE [#1000 EQ 0] DO1` … `END1`. Anything else is refused with its line.

use super::plant::Plant;
use crate::run::Dialect;
use std::time::{Duration, Instant};
use thiserror::Error;

/// A refused program line.
#[derive(Clone, Debug, Error, PartialEq)]
#[error("part program line {line}: {problem}: \"{text}\"")]
pub struct ProgramError {
    pub line: usize,
    pub text: String,
    pub problem: String,
}

/// One thing the CNC does.
#[derive(Clone, Debug, PartialEq)]
pub enum Op {
    /// Move the axis to `to_mm` at `feed_mm_min`.
    Move { to_mm: f64, feed_mm_min: f64 },
    /// Wait.
    Dwell(Duration),
    /// Put the target code on the handshake output.
    Code(u32),
    /// Raise or lower "at target".
    AtTarget(bool),
    /// Wait until the PLC says "captured" (or the timeout passes).
    WaitCaptured(Duration),
    /// Program end.
    End,
}

fn err(line: usize, text: &str, problem: impl Into<String>) -> ProgramError {
    ProgramError {
        line,
        text: text.to_string(),
        problem: problem.into(),
    }
}

/// The longest dwell or wait a program may ask for.
const MAX_WAIT_S: f64 = 86_400.0;

/// A dwell or wait of `secs` (at least 0) as a duration; longer than a day is an error
/// (a huge P word overflowed `Duration`: found by tests/it/fuzz.rs).
fn wait_time(ln: usize, raw: &str, what: &str, secs: f64) -> Result<Duration, ProgramError> {
    if secs <= MAX_WAIT_S {
        Ok(Duration::from_secs_f64(secs))
    } else {
        Err(err(
            ln,
            raw,
            format!("{what} of {secs:.0} s is longer than a day"),
        ))
    }
}

/// Parse program text in `dialect` for `axis` ("X", "Y" or "Z").
pub fn parse(text: &str, dialect: Dialect, axis: &str) -> Result<Vec<Op>, ProgramError> {
    if !matches!(dialect, Dialect::Iso | Dialect::LinuxCnc) {
        return Err(err(
            0,
            "",
            format!(
                "the twin's CNC runs ISO/Fanuc and LinuxCNC programs, not {}",
                dialect.name()
            ),
        ));
    }
    let axis = axis.chars().next().unwrap_or('X').to_ascii_uppercase();
    let mut ops = Vec::new();
    let mut feed = None::<f64>;
    let mut in_wait = false;
    for (i, raw) in text.lines().enumerate() {
        let ln = i + 1;
        // Strip comments and blanks.
        let mut line = String::new();
        let mut depth = 0;
        for c in raw.chars() {
            match c {
                '(' => depth += 1,
                ')' if depth > 0 => depth -= 1,
                _ if depth == 0 => line.push(c),
                _ => {}
            }
        }
        let line = line.trim().to_ascii_uppercase();
        if line.is_empty()
            || line == "%"
            || (line.starts_with('O') && line[1..].chars().all(|c| c.is_ascii_digit()))
        {
            continue;
        }
        // Fanuc macro statements.
        if let Some(rest) = line.strip_prefix('#') {
            let (var, value) = rest
                .split_once('=')
                .ok_or_else(|| err(ln, raw, "a macro line must be #n = value"))?;
            let var: u32 = var
                .trim()
                .parse()
                .map_err(|_| err(ln, raw, "bad variable number"))?;
            let value: f64 = value
                .trim()
                .parse()
                .map_err(|_| err(ln, raw, "bad value"))?;
            match var {
                1132..=1135 => ops.push(Op::Code(value as u32)),
                1100..=1131 => ops.push(Op::AtTarget(value != 0.0)),
                _ => {
                    return Err(err(
                        ln,
                        raw,
                        format!("variable #{var} is not a handshake output"),
                    ));
                }
            }
            continue;
        }
        if line.starts_with("WHILE") {
            if !line.contains("EQ 0") {
                return Err(err(
                    ln,
                    raw,
                    "only WHILE [#n EQ 0] DO1 (wait for captured) is supported",
                ));
            }
            ops.push(Op::WaitCaptured(Duration::from_secs(3600)));
            in_wait = true;
            continue;
        }
        if line.starts_with("END") && in_wait {
            in_wait = false;
            continue;
        }
        // Words: letter + number.
        let mut words: Vec<(char, f64)> = Vec::new();
        let chars: Vec<char> = line.chars().filter(|c| !c.is_whitespace()).collect();
        let mut k = 0;
        while k < chars.len() {
            let letter = chars[k];
            if !letter.is_ascii_alphabetic() {
                return Err(err(ln, raw, format!("unexpected '{letter}'")));
            }
            k += 1;
            let start = k;
            while k < chars.len()
                && (chars[k].is_ascii_digit()
                    || chars[k] == '.'
                    || chars[k] == '-'
                    || chars[k] == '+')
            {
                k += 1;
            }
            let num: String = chars[start..k].iter().collect();
            let v: f64 = num
                .parse()
                .map_err(|_| err(ln, raw, format!("word {letter} has no number")))?;
            words.push((letter, v));
        }
        let get = |c: char| words.iter().find(|(l, _)| *l == c).map(|(_, v)| *v);
        if let Some(f) = get('F') {
            if f.is_nan() || f <= 0.0 {
                return Err(err(ln, raw, "feed must be positive"));
            }
            feed = Some(f);
        }
        let gs: Vec<u32> = words
            .iter()
            .filter(|(l, _)| *l == 'G')
            .map(|(_, v)| *v as u32)
            .collect();
        let ms: Vec<u32> = words
            .iter()
            .filter(|(l, _)| *l == 'M')
            .map(|(_, v)| *v as u32)
            .collect();
        for g in &gs {
            match g {
                0 | 1 => {
                    let to = get(axis)
                        .ok_or_else(|| err(ln, raw, format!("a move needs a {axis} word")))?;
                    let f = if *g == 0 {
                        Some(feed.unwrap_or(60_000.0).max(60_000.0))
                    } else {
                        feed
                    };
                    let f = f.ok_or_else(|| err(ln, raw, "no feed programmed (F)"))?;
                    ops.push(Op::Move {
                        to_mm: to,
                        feed_mm_min: f,
                    });
                }
                4 => {
                    let secs = match dialect {
                        Dialect::LinuxCnc => get('P'),
                        _ => get('P').map(|p| p / 1000.0).or(get('X')),
                    }
                    .ok_or_else(|| err(ln, raw, "a dwell needs its time"))?;
                    if secs.is_nan() || secs < 0.0 {
                        return Err(err(ln, raw, "negative dwell"));
                    }
                    ops.push(Op::Dwell(wait_time(ln, raw, "dwell", secs)?));
                }
                17 | 21 | 90 | 94 => {}
                other => {
                    return Err(err(
                        ln,
                        raw,
                        format!("G{other} is not supported by the twin's CNC"),
                    ));
                }
            }
        }
        for m in &ms {
            match m {
                2 | 30 => ops.push(Op::End),
                68 => ops.push(Op::Code(
                    get('Q').ok_or_else(|| err(ln, raw, "M68 needs Q"))? as u32,
                )),
                64 => ops.push(Op::AtTarget(true)),
                65 => ops.push(Op::AtTarget(false)),
                66 => ops.push(Op::WaitCaptured(wait_time(
                    ln,
                    raw,
                    "M66 wait (Q)",
                    get('Q').unwrap_or(3600.0).max(0.0),
                )?)),
                other => {
                    return Err(err(
                        ln,
                        raw,
                        format!("M{other} is not supported by the twin's CNC"),
                    ));
                }
            }
        }
        if gs.is_empty() && ms.is_empty() && get('F').is_none() {
            return Err(err(ln, raw, "no G, M or F word"));
        }
    }
    Ok(ops)
}

/// The handshake signals between the twin's CNC and the PLC side.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Handshake {
    /// The target code last output.
    pub code: u32,
    /// "At target" raised.
    pub at_target: bool,
}

#[derive(Clone, Debug, PartialEq)]
enum State {
    Ready,
    Moving { until: Instant },
    Dwelling { until: Instant },
    Waiting { until: Instant },
    Done,
}

/// Executes a program against the plant.
#[derive(Clone, Debug)]
pub struct Cnc {
    ops: Vec<Op>,
    pc: usize,
    state: State,
    pub handshake: Handshake,
    pub started: Option<Instant>,
    pub finished: Option<Instant>,
    /// Stop the program when the move in progress ends (feed hold at the next stop, then
    /// reset), as an operator or the service does when a run pauses.
    stop_requested: bool,
}

impl Cnc {
    /// A CNC with `ops` loaded, not yet started.
    pub fn new(ops: Vec<Op>) -> Self {
        Cnc {
            ops,
            pc: 0,
            state: State::Ready,
            handshake: Handshake::default(),
            started: None,
            finished: None,
            stop_requested: false,
        }
    }

    /// Stop the program at its next stop: the move in progress ends, nothing after it runs.
    pub fn stop_at_next_stop(&mut self) {
        self.stop_requested = true;
    }

    /// Whether the program has ended.
    pub fn is_done(&self) -> bool {
        self.state == State::Done
    }

    /// When the CNC next needs a `step` (None while waiting for the handshake only).
    pub fn next_wake(&self) -> Option<Instant> {
        match self.state {
            State::Moving { until } | State::Dwelling { until } | State::Waiting { until } => {
                Some(until)
            }
            _ => None,
        }
    }

    /// Advance to `now`. `captured` is the PLC's "captured" input for the current wait.
    pub fn step(&mut self, now: Instant, plant: &Plant, captured: bool) {
        self.started.get_or_insert(now);
        loop {
            match self.state {
                State::Done => return,
                State::Moving { until } | State::Dwelling { until } if now < until => return,
                State::Waiting { until } if !captured && now < until => return,
                _ => {}
            }
            if self.stop_requested {
                self.state = State::Done;
                self.finished = Some(now);
                return;
            }
            let Some(op) = self.ops.get(self.pc).cloned() else {
                self.state = State::Done;
                self.finished = Some(now);
                return;
            };
            self.pc += 1;
            match op {
                Op::Move { to_mm, feed_mm_min } => {
                    plant.set_feed(feed_mm_min / 60.0);
                    plant.move_carriage(to_mm, now);
                    self.state = State::Moving {
                        until: plant.carriage_move_end(),
                    };
                }
                Op::Dwell(d) => self.state = State::Dwelling { until: now + d },
                Op::Code(c) => {
                    self.handshake.code = c;
                    self.state = State::Ready;
                }
                Op::AtTarget(on) => {
                    self.handshake.at_target = on;
                    self.state = State::Ready;
                }
                Op::WaitCaptured(t) => {
                    self.state = State::Waiting { until: now + t };
                    if !captured {
                        return;
                    }
                }
                Op::End => {
                    self.state = State::Done;
                    self.finished = Some(now);
                    return;
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::optics::Layout;
    use crate::run::program::{CaptureMode, Handshake as Hs, generate};
    use crate::run::{Plan, PlanSpec};
    use crate::sim::plant::PlantSpec;

    fn plan() -> Plan {
        Plan::new(PlanSpec {
            axis: "X".into(),
            start_mm: 0.0,
            end_mm: 100.0,
            targets: 5,
            runs: 2,
            overrun_mm: 2.0,
            dwell_s: 0.5,
            feed_mm_min: 3000.0,
            lead_mm: 0.0,
            reference_mm: None,
        })
        .unwrap()
    }

    #[test]
    fn parses_what_the_service_writes() {
        let p = plan();
        for dialect in [Dialect::Iso, Dialect::LinuxCnc] {
            let text = generate(&p, dialect, CaptureMode::Stability).unwrap();
            let ops = parse(&text, dialect, "X").unwrap();
            let moves: Vec<f64> = ops
                .iter()
                .filter_map(|o| match o {
                    Op::Move { to_mm, .. } => Some(*to_mm),
                    _ => None,
                })
                .collect();
            let want: Vec<f64> = p
                .steps()
                .iter()
                .map(|s| (s.position_mm * 1e4).round() / 1e4)
                .collect();
            assert_eq!(moves, want, "{dialect:?}");
            let dwells = ops
                .iter()
                .filter(|o| **o == Op::Dwell(Duration::from_millis(500)))
                .count();
            assert_eq!(dwells, p.capture_count(), "{dialect:?}: dwell units");
            assert_eq!(ops.last(), Some(&Op::End));
            let hs = generate(&p, dialect, CaptureMode::Handshake(Hs::default())).unwrap();
            let ops = parse(&hs, dialect, "X").unwrap();
            assert!(ops.contains(&Op::Code(1000)));
            assert_eq!(
                ops.iter()
                    .filter(|o| matches!(o, Op::WaitCaptured(_)))
                    .count(),
                p.capture_count()
            );
        }
    }

    #[test]
    fn refuses_what_it_cannot_run_naming_the_line() {
        let e = parse("G21 G90\nG91 X10 F100\n", Dialect::LinuxCnc, "X").unwrap_err();
        assert_eq!(e.line, 2);
        assert!(e.to_string().contains("G91"), "{e}");
        let e = parse("G1 X10\n", Dialect::LinuxCnc, "X").unwrap_err();
        assert!(e.problem.contains("no feed"), "{e}");
        let e = parse("G1 Y10 F100\n", Dialect::LinuxCnc, "X").unwrap_err();
        assert!(e.problem.contains("X word"), "{e}");
        assert!(parse("G1 X1 F1\n", Dialect::Siemens, "X").is_err());
        // A dwell too long for a Duration is an error, not a panic (found by fuzzing).
        let e = parse("G04 P184467440737095516161500\n", Dialect::Iso, "X").unwrap_err();
        assert_eq!(e.line, 1);
        assert!(e.problem.contains("longer than a day"), "{e}");
        // 401 digits parse as infinity.
        let inf = format!("M66 Q1{}\n", "0".repeat(400));
        assert!(parse(&inf, Dialect::LinuxCnc, "X").is_err());
        assert!(parse("G04 P86400\n", Dialect::LinuxCnc, "X").is_ok());
    }

    #[test]
    fn runs_the_cycle_on_the_plant() {
        let t0 = crate::util::clock::now();
        let plant = Plant::new(&Layout::reference(), &PlantSpec::default(), t0).unwrap();
        let p = plan();
        let ops = parse(
            &generate(&p, Dialect::LinuxCnc, CaptureMode::Stability).unwrap(),
            Dialect::LinuxCnc,
            "X",
        )
        .unwrap();
        // The cycle starts with the axis at its first stop.
        plant.move_carriage(p.steps()[0].position_mm, t0);
        let mut now = plant.carriage_move_end();
        let mut cnc = Cnc::new(ops);
        let mut rests = Vec::new();
        while !cnc.is_done() {
            cnc.step(now, &plant, false);
            if let Some(w) = cnc.next_wake() {
                now = w.max(now + Duration::from_millis(1));
            }
            let (pos, moving) = plant.carriage(now);
            if !moving && rests.last() != Some(&pos) {
                rests.push(pos);
            }
        }
        // Every stop of the cycle, in order.
        let stops: Vec<f64> = p.steps().iter().map(|s| s.position_mm).collect();
        let mut want = stops.clone();
        want.dedup();
        let mut got = rests.clone();
        got.dedup();
        assert!(got.ends_with(&want[1..]), "{got:?}");
        // The program took its motion plus dwell time (feed 50 mm/s, plant accel 500 mm/s²).
        let took = cnc.finished.unwrap() - cnc.started.unwrap();
        let expect = p.motion_time_s(500.0);
        assert!(
            (took.as_secs_f64() - expect).abs() < 0.05,
            "{took:?} vs {expect}"
        );
    }
}
