//! PI GCS 2.0 (C-887 hexapod controllers) over TCP, sans-I/O.
//!
//! Commands are ASCII lines ended by LF; set commands have no answer, so each is followed by
//! `ERR?` (answered with the error code, `0` when none). Query answers are one line per axis,
//! `X=1.2345`, every line but the last ending with a space before the LF (how pipython's
//! `eol` tells a multi-line answer is complete). Axes of the hexapod are X Y Z (mm) and U V W
//! (degrees); the pivot point is set with `SPI R r S s T t` (only with U, V, W at 0: error 9),
//! a work coordinate system with `KSD name X .. Y .. Z .. U .. V .. W ..` and enabled with
//! `KEN name`. The controller has no error-text query: the texts below are the manual's.

use super::exchange::Exchange;
use super::{AXES, Command, HexPose, HexapodError, Protocol, Reply, wire_number};

const CONTROLLER: &str = "PI C-887";

/// The name of the coordinate system this driver defines with `KSD`.
pub const WORK_CS: &str = "AXISCOMP";

/// The text of a GCS error code, as the C-887 manual (and pipython's `gcserror`) word it.
pub fn error_text(code: i64) -> &'static str {
    match code {
        0 => "No error",
        1 => "Parameter syntax error",
        2 => "Unknown command",
        5 => "Unallowable move attempted on unreferenced axis, or move attempted with servo off",
        7 => "Position out of limits",
        8 => "Velocity out of limits",
        9 => "Attempt to set pivot point while U,V and W not all 0",
        10 => "Controller was stopped by command",
        15 => "Invalid axis identifier",
        17 => "Parameter out of range",
        1024 | -1024 => {
            "Motion error: position error too large, servo is switched off automatically"
        }
        _ => "(no text for this code in axiscomp's table: see the controller's manual)",
    }
}

#[derive(Clone, Copy, Debug, PartialEq)]
enum Expect {
    /// The answer to `ERR?`: one integer.
    ErrCode,
    /// One line of text.
    Line,
    /// One `axis=value` line per hexapod axis.
    Axes,
}

type Step = (String, Expect);

fn set(cmd: String) -> Step {
    (format!("{cmd}\nERR?\n"), Expect::ErrCode)
}

fn query(cmd: &str, expect: Expect) -> Step {
    (format!("{cmd}\n"), expect)
}

fn axes_args(v: &[f64]) -> String {
    AXES.iter()
        .zip(v)
        .map(|(a, x)| format!("{a} {}", wire_number(*x)))
        .collect::<Vec<_>>()
        .join(" ")
}

/// The GCS 2.0 machine.
#[derive(Debug)]
pub struct Gcs {
    x: Exchange<Expect>,
}

impl Default for Gcs {
    fn default() -> Self {
        Gcs { x: Exchange::new() }
    }
}

/// Whether `buf` holds a whole GCS answer: it ends with LF not preceded by a space.
pub fn answer_complete(buf: &[u8]) -> bool {
    match buf {
        [.., b' ', b'\n'] => false,
        [.., b'\n'] => true,
        _ => false,
    }
}

/// Parse `X=1 \nY=2 \n...W=6\n` into the six values, in axis order.
pub fn parse_axes(text: &str) -> Option<[f64; 6]> {
    let mut v = [f64::NAN; 6];
    let mut seen = 0;
    for line in text.lines().map(str::trim).filter(|l| !l.is_empty()) {
        let (axis, value) = line.split_once('=')?;
        let k = AXES.iter().position(|a| *a == axis.trim())?;
        v[k] = value.trim().parse().ok()?;
        seen |= 1 << k;
    }
    (seen == 0b11_1111).then_some(v)
}

impl Gcs {
    pub fn new() -> Self {
        Gcs::default()
    }

    /// The requests of `cmd`, in order.
    fn steps(cmd: &Command) -> Vec<Step> {
        match cmd {
            Command::Identify => vec![query("*IDN?", Expect::Line)],
            Command::Initialize => {
                vec![set("SVO X 1 Y 1 Z 1 U 1 V 1 W 1".into()), set("FRF".into())]
            }
            Command::Referenced => vec![query("FRF?", Expect::Axes)],
            Command::SetPivot(p) => vec![set(format!(
                "SPI R {} S {} T {}",
                wire_number(p[0]),
                wire_number(p[1]),
                wire_number(p[2])
            ))],
            Command::SetWork(p) => vec![
                set(format!("KSD {WORK_CS} {}", axes_args(&p.0))),
                set(format!("KEN {WORK_CS}")),
            ],
            Command::Move(p) => vec![set(format!("MOV {}", axes_args(&p.0)))],
            Command::Position => vec![query("POS?", Expect::Axes)],
            // A motion error (following error) shows only in the error register.
            Command::OnTarget => vec![query("ONT?", Expect::Axes), query("ERR?", Expect::ErrCode)],
            Command::Stop => vec![set("STP".into())],
            Command::SetSpeed(v) => vec![set(format!("VLS {}", wire_number(*v)))],
        }
    }

    fn protocol_error(&self, reply: &str) -> HexapodError {
        HexapodError::Protocol {
            controller: CONTROLLER,
            command: self.current(),
            reply: reply.trim_end().escape_debug().to_string(),
        }
    }

    fn answer(&mut self, text: &str) {
        let Some((_, expect)) = self.x.current.clone() else {
            return;
        };
        let cmd = self.x.cmd.unwrap_or(Command::Identify);
        match expect {
            Expect::ErrCode => match text.trim().parse::<i64>() {
                // STP reports itself as error 10.
                Ok(0) => self.x.next(),
                Ok(10) if cmd == Command::Stop => self.x.next(),
                Ok(code) => self.x.fail(HexapodError::Controller {
                    controller: CONTROLLER,
                    code,
                    text: error_text(code).into(),
                }),
                Err(_) => self.x.fail(self.protocol_error(text)),
            },
            Expect::Line => {
                self.x.outcome = Some(Ok(Reply::Text(text.trim().to_string())));
                self.x.next();
            }
            Expect::Axes => match parse_axes(text) {
                Some(v) => {
                    self.x.outcome = Some(Ok(match cmd {
                        Command::Position => Reply::Pose(HexPose(v)),
                        _ => Reply::Flag(v.iter().all(|x| *x == 1.0)),
                    }));
                    self.x.next();
                }
                None => self.x.fail(self.protocol_error(text)),
            },
        }
    }
}

impl Protocol for Gcs {
    fn controller(&self) -> &'static str {
        CONTROLLER
    }

    fn start(&mut self, cmd: Command) {
        self.x.start(cmd, Gcs::steps(&cmd));
    }

    fn poll_transmit(&mut self) -> Option<Vec<u8>> {
        self.x.poll_transmit()
    }

    fn handle_input(&mut self, data: &[u8]) {
        self.x.buf.extend_from_slice(data);
        while self.x.current.is_some() && answer_complete(&self.x.buf) {
            // One answer per request: answers are never pipelined by this machine.
            let text = String::from_utf8_lossy(&self.x.buf).into_owned();
            self.x.buf.clear();
            self.answer(&text);
        }
    }

    fn poll_outcome(&mut self) -> Option<Result<Reply, HexapodError>> {
        self.x.poll_outcome()
    }

    fn current(&self) -> String {
        self.x
            .request()
            .map(|s| format!("\"{}\"", s.escape_debug()))
            .unwrap_or_else(|| "no request".into())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sent(m: &mut Gcs) -> String {
        let mut s = String::new();
        while let Some(b) = m.poll_transmit() {
            s.push_str(&String::from_utf8(b).unwrap());
        }
        s
    }

    /// The C-887 manual's syntax: `MOV X 10 Y 5`-style pairs, `ERR?` after a set command.
    #[test]
    fn move_is_mov_with_axis_value_pairs_then_err() {
        let mut m = Gcs::new();
        m.start(Command::Move(HexPose([0.1, -2.0, 0.0, 0.01, 0.0, -0.0125])));
        assert_eq!(
            sent(&mut m),
            "MOV X 0.1 Y -2 Z 0 U 0.01 V 0 W -0.0125\nERR?\n"
        );
        assert_eq!(m.poll_outcome(), None);
        m.handle_input(b"0\n");
        assert_eq!(m.poll_outcome(), Some(Ok(Reply::Done)));
    }

    #[test]
    fn an_error_code_carries_the_manuals_text() {
        let mut m = Gcs::new();
        m.start(Command::Move(HexPose([50.0, 0.0, 0.0, 0.0, 0.0, 0.0])));
        sent(&mut m);
        m.handle_input(b"7\n");
        assert_eq!(
            m.poll_outcome(),
            Some(Err(HexapodError::Controller {
                controller: "PI C-887",
                code: 7,
                text: "Position out of limits".into()
            }))
        );
    }

    /// Multi-line answers: every line but the last ends with a space before LF.
    #[test]
    fn position_waits_for_the_last_line() {
        let mut m = Gcs::new();
        m.start(Command::Position);
        assert_eq!(sent(&mut m), "POS?\n");
        m.handle_input(b"X=0.1000000 \nY=-2.0000000 \nZ=0.0000000 \n");
        assert_eq!(m.poll_outcome(), None);
        m.handle_input(b"U=0.0100000 \nV=0.0000000 \nW=-0.0125000\n");
        assert_eq!(
            m.poll_outcome(),
            Some(Ok(Reply::Pose(HexPose([
                0.1, -2.0, 0.0, 0.01, 0.0, -0.0125
            ]))))
        );
    }

    #[test]
    fn on_target_is_all_ones() {
        let mut m = Gcs::new();
        m.start(Command::OnTarget);
        assert_eq!(sent(&mut m), "ONT?\n");
        m.handle_input(b"X=1 \nY=1 \nZ=0 \nU=1 \nV=1 \nW=1\n");
        assert_eq!(m.poll_outcome(), None);
        assert_eq!(sent(&mut m), "ERR?\n");
        m.handle_input(b"0\n");
        assert_eq!(m.poll_outcome(), Some(Ok(Reply::Flag(false))));
        m.start(Command::OnTarget);
        sent(&mut m);
        m.handle_input(b"X=1 \nY=1 \nZ=1 \nU=1 \nV=1 \nW=1\n");
        m.handle_input(b"0\n");
        assert_eq!(m.poll_outcome(), Some(Ok(Reply::Flag(true))));
        // A following error: not on target, and the register says why.
        m.start(Command::OnTarget);
        sent(&mut m);
        m.handle_input(b"X=0 \nY=0 \nZ=0 \nU=0 \nV=0 \nW=0\n");
        m.handle_input(b"-1024\n");
        assert!(matches!(
            m.poll_outcome(),
            Some(Err(HexapodError::Controller { code: -1024, .. }))
        ));
    }

    #[test]
    fn coordinate_systems_pivot_and_init() {
        let mut m = Gcs::new();
        m.start(Command::SetPivot([0.0, 0.0, 120.5]));
        assert_eq!(sent(&mut m), "SPI R 0 S 0 T 120.5\nERR?\n");
        m.handle_input(b"0\n");
        assert_eq!(m.poll_outcome(), Some(Ok(Reply::Done)));

        m.start(Command::SetWork(HexPose([1.0, 2.0, 3.0, 0.0, 0.0, 90.0])));
        assert_eq!(
            sent(&mut m),
            "KSD AXISCOMP X 1 Y 2 Z 3 U 0 V 0 W 90\nERR?\n"
        );
        m.handle_input(b"0\n");
        assert_eq!(m.poll_outcome(), None);
        assert_eq!(sent(&mut m), "KEN AXISCOMP\nERR?\n");
        m.handle_input(b"0\n");
        assert_eq!(m.poll_outcome(), Some(Ok(Reply::Done)));

        m.start(Command::SetSpeed(2.5));
        assert_eq!(sent(&mut m), "VLS 2.5\nERR?\n");
        m.handle_input(b"0\n");
        assert_eq!(m.poll_outcome(), Some(Ok(Reply::Done)));

        m.start(Command::Initialize);
        assert_eq!(sent(&mut m), "SVO X 1 Y 1 Z 1 U 1 V 1 W 1\nERR?\n");
        m.handle_input(b"0\n");
        assert_eq!(sent(&mut m), "FRF\nERR?\n");
        m.handle_input(b"0\n");
        assert_eq!(m.poll_outcome(), Some(Ok(Reply::Done)));
    }

    #[test]
    fn stop_accepts_its_own_error_10_and_garbage_is_named() {
        let mut m = Gcs::new();
        m.start(Command::Stop);
        assert_eq!(sent(&mut m), "STP\nERR?\n");
        m.handle_input(b"10\n");
        assert_eq!(m.poll_outcome(), Some(Ok(Reply::Done)));

        m.start(Command::Position);
        sent(&mut m);
        m.handle_input(b"Q=1\n");
        match m.poll_outcome() {
            Some(Err(HexapodError::Protocol { command, reply, .. })) => {
                assert_eq!(command, "\"POS?\"");
                assert_eq!(reply, "Q=1");
            }
            other => panic!("{other:?}"),
        }
    }
}
