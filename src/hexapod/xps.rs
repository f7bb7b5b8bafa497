//! Newport HXP hexapod controllers: the XPS API over TCP (port 5001), sans-I/O.
//!
//! A request is a function call in ASCII, `HexapodMoveAbsolute(HEXAPOD,Work,x,y,z,u,v,w)`,
//! output arguments written as their C types (`GroupStatusGet(HEXAPOD,int *)`); the answer is
//! `code,outputs,EndOfAPI` (code 0: success; outputs comma-separated, empty when none). Calls
//! block until done: `HexapodMoveAbsolute` answers when the move has ended. A non-zero code is
//! turned into the controller's own text with `ErrorStringGet(code,char *)`. Coordinate
//! systems: `Work` (where poses are given) and `Tool` (its origin is the pivot point), set
//! with `HexapodCoordinateSystemSet`. Group states (`GroupStatusGet`): 10 to 19 are ready
//! states (11 after homing, 12 after a move), 42 not referenced, 43 homing, 44 moving.
//!
//! Speed: `HexapodMoveAbsolute` takes no velocity; the platform moves with the SGamma
//! profiles of its six actuators, the positioners `HEXAPOD.1` to `HEXAPOD.6`. The speed is set
//! as Newport's own client sets a positioner's (`newportxps`' `set_velocity`): read each
//! actuator's `PositionerSGammaParametersGet(HEXAPOD.n,double *,double *,double *,double *)`
//! (velocity, acceleration, minimum and maximum jerk time) and write it back with the new
//! velocity, `PositionerSGammaParametersSet(HEXAPOD.n,v,a,tmin,tmax)`.

use super::exchange::Exchange;
use super::{Command, HexPose, HexapodError, Protocol, Reply, wire_number};

const CONTROLLER: &str = "Newport HXP";
const SUFFIX: &str = "EndOfAPI";

/// Whether a group status is one of the ready states.
pub fn is_ready(status: i64) -> bool {
    (10..=19).contains(&status)
}

#[derive(Clone, Copy, Debug, PartialEq)]
enum Expect {
    Nothing,
    Text,
    Status,
    Pose,
    /// The text of the error `code` (the reply to `ErrorStringGet`).
    ErrorText(i64),
    /// An actuator's SGamma parameters, to write back with this velocity (mm/s).
    SGamma(usize, f64),
}

type Step = (String, Expect);

fn call(send: String, expect: Expect) -> Step {
    (send, expect)
}

fn six(p: &HexPose) -> String {
    p.0.iter()
        .map(|v| wire_number(*v))
        .collect::<Vec<_>>()
        .join(",")
}

/// Split `code,outputs,EndOfAPI` into the code and the outputs.
pub fn split_reply(text: &str) -> Option<(i64, &str)> {
    let body = text.strip_suffix(SUFFIX)?;
    let body = body.strip_suffix(',').unwrap_or(body);
    let (code, rest) = match body.split_once(',') {
        Some((c, r)) => (c, r),
        None => (body, ""),
    };
    Some((code.trim().parse().ok()?, rest))
}

/// The XPS machine for one positioner group (`HEXAPOD` on an HXP).
#[derive(Debug)]
pub struct Xps {
    group: String,
    x: Exchange<Expect>,
}

impl Xps {
    pub fn new(group: &str) -> Self {
        Xps {
            group: group.to_string(),
            x: Exchange::new(),
        }
    }

    fn steps(&self, cmd: &Command) -> Vec<Step> {
        let g = &self.group;
        match cmd {
            Command::Identify => vec![call("FirmwareVersionGet(char *)".into(), Expect::Text)],
            Command::Initialize => vec![
                call(format!("GroupKill({g})"), Expect::Nothing),
                call(format!("GroupInitialize({g})"), Expect::Nothing),
                call(format!("GroupHomeSearch({g})"), Expect::Nothing),
            ],
            Command::Referenced | Command::OnTarget => {
                vec![call(format!("GroupStatusGet({g},int *)"), Expect::Status)]
            }
            Command::SetPivot(p) => vec![call(
                format!(
                    "HexapodCoordinateSystemSet({g},Tool,{},{},{},0,0,0)",
                    wire_number(p[0]),
                    wire_number(p[1]),
                    wire_number(p[2])
                ),
                Expect::Nothing,
            )],
            Command::SetWork(p) => vec![call(
                format!("HexapodCoordinateSystemSet({g},Work,{})", six(p)),
                Expect::Nothing,
            )],
            Command::Move(p) => vec![call(
                format!("HexapodMoveAbsolute({g},Work,{})", six(p)),
                Expect::Nothing,
            )],
            Command::Position => vec![call(
                format!(
                    "HexapodPositionCurrentGet({g},Work,double *,double *,double *,double *,double *,double *)"
                ),
                Expect::Pose,
            )],
            Command::Stop => vec![call(format!("GroupMoveAbort({g})"), Expect::Nothing)],
            Command::SetSpeed(v) => (1..=6)
                .map(|n| {
                    call(
                        format!(
                            "PositionerSGammaParametersGet({g}.{n},double *,double *,double *,double *)"
                        ),
                        Expect::SGamma(n, *v),
                    )
                })
                .collect(),
        }
    }

    fn protocol_error(&self, reply: &str) -> HexapodError {
        HexapodError::Protocol {
            controller: CONTROLLER,
            command: self.current(),
            reply: reply.escape_debug().to_string(),
        }
    }

    fn answer(&mut self, text: &str) {
        let Some((_, expect)) = self.x.current.clone() else {
            return;
        };
        let Some((code, rest)) = split_reply(text) else {
            return self.x.fail(self.protocol_error(text));
        };
        if let Expect::ErrorText(orig) = expect {
            let text = if code == 0 && !rest.is_empty() {
                rest.to_string()
            } else {
                format!("(ErrorStringGet answered {code})")
            };
            return self.x.fail(HexapodError::Controller {
                controller: CONTROLLER,
                code: orig,
                text,
            });
        }
        if code != 0 {
            // Ask the controller for its own text of the code, then fail with both.
            return self.x.instead(call(
                format!("ErrorStringGet({code},char *)"),
                Expect::ErrorText(code),
            ));
        }
        let parsed = match expect {
            Expect::Nothing => None,
            Expect::Text => Some(Reply::Text(rest.to_string())),
            Expect::Status => match rest.trim().parse::<i64>() {
                Ok(s) => Some(Reply::Flag(match self.x.cmd {
                    Some(Command::OnTarget) => s == 12 || s == 11 || s == 10,
                    _ => is_ready(s),
                })),
                Err(_) => return self.x.fail(self.protocol_error(text)),
            },
            Expect::Pose => {
                let v: Vec<f64> = rest
                    .split(',')
                    .filter_map(|x| x.trim().parse().ok())
                    .collect();
                match <[f64; 6]>::try_from(v) {
                    Ok(a) => Some(Reply::Pose(HexPose(a))),
                    Err(_) => return self.x.fail(self.protocol_error(text)),
                }
            }
            Expect::ErrorText(_) => None,
            Expect::SGamma(n, v) => {
                let p: Vec<f64> = rest
                    .split(',')
                    .filter_map(|x| x.trim().parse().ok())
                    .collect();
                let [_, acc, tmin, tmax] = p[..] else {
                    return self.x.fail(self.protocol_error(text));
                };
                let set = format!(
                    "PositionerSGammaParametersSet({}.{n},{},{},{},{})",
                    self.group,
                    wire_number(v),
                    wire_number(acc),
                    wire_number(tmin),
                    wire_number(tmax)
                );
                return self.x.then(call(set, Expect::Nothing));
            }
        };
        if let Some(r) = parsed {
            self.x.outcome = Some(Ok(r));
        }
        self.x.next();
    }
}

impl Protocol for Xps {
    fn controller(&self) -> &'static str {
        CONTROLLER
    }

    fn start(&mut self, cmd: Command) {
        let steps = self.steps(&cmd);
        self.x.start(cmd, steps);
    }

    fn poll_transmit(&mut self) -> Option<Vec<u8>> {
        self.x.poll_transmit()
    }

    fn handle_input(&mut self, data: &[u8]) {
        self.x.buf.extend_from_slice(data);
        while self.x.current.is_some() {
            let text = String::from_utf8_lossy(&self.x.buf).into_owned();
            let Some(end) = text.find(SUFFIX) else {
                return;
            };
            let one = text[..end + SUFFIX.len()].to_string();
            self.x.buf.drain(..one.len());
            self.answer(&one);
        }
    }

    fn poll_outcome(&mut self) -> Option<Result<Reply, HexapodError>> {
        self.x.poll_outcome()
    }

    fn current(&self) -> String {
        self.x.request().unwrap_or("no request").to_string()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sent(m: &mut Xps) -> String {
        let mut s = String::new();
        while let Some(b) = m.poll_transmit() {
            s.push_str(&String::from_utf8(b).unwrap());
        }
        s
    }

    /// The HXP manual's call, answered `0,,EndOfAPI` when it has no outputs.
    #[test]
    fn move_absolute_in_work() {
        let mut m = Xps::new("HEXAPOD");
        m.start(Command::Move(HexPose([0.1, -2.0, 0.0, 0.01, 0.0, -0.0125])));
        assert_eq!(
            sent(&mut m),
            "HexapodMoveAbsolute(HEXAPOD,Work,0.1,-2,0,0.01,0,-0.0125)"
        );
        m.handle_input(b"0,,EndOf");
        assert_eq!(m.poll_outcome(), None);
        m.handle_input(b"API");
        assert_eq!(m.poll_outcome(), Some(Ok(Reply::Done)));
    }

    /// A failing call: the code, then the controller's text from `ErrorStringGet`.
    #[test]
    fn an_error_asks_the_controller_for_its_text() {
        let mut m = Xps::new("HEXAPOD");
        m.start(Command::Move(HexPose([0.0; 6])));
        sent(&mut m);
        m.handle_input(b"-25,,EndOfAPI");
        assert_eq!(m.poll_outcome(), None);
        assert_eq!(sent(&mut m), "ErrorStringGet(-25,char *)");
        m.handle_input(b"0,Following Error,EndOfAPI");
        assert_eq!(
            m.poll_outcome(),
            Some(Err(HexapodError::Controller {
                controller: "Newport HXP",
                code: -25,
                text: "Following Error".into()
            }))
        );
    }

    #[test]
    fn position_and_status() {
        let mut m = Xps::new("HEXAPOD");
        m.start(Command::Position);
        assert_eq!(
            sent(&mut m),
            "HexapodPositionCurrentGet(HEXAPOD,Work,double *,double *,double *,double *,double *,double *)"
        );
        m.handle_input(b"0,0.1,-2,0,0.01,0,-0.0125,EndOfAPI");
        assert_eq!(
            m.poll_outcome(),
            Some(Ok(Reply::Pose(HexPose([
                0.1, -2.0, 0.0, 0.01, 0.0, -0.0125
            ]))))
        );
        m.start(Command::OnTarget);
        assert_eq!(sent(&mut m), "GroupStatusGet(HEXAPOD,int *)");
        m.handle_input(b"0,44,EndOfAPI");
        assert_eq!(m.poll_outcome(), Some(Ok(Reply::Flag(false))));
        m.start(Command::OnTarget);
        sent(&mut m);
        m.handle_input(b"0,12,EndOfAPI");
        assert_eq!(m.poll_outcome(), Some(Ok(Reply::Flag(true))));
    }

    #[test]
    fn init_pivot_and_work() {
        let mut m = Xps::new("HEXAPOD");
        m.start(Command::Initialize);
        assert_eq!(sent(&mut m), "GroupKill(HEXAPOD)");
        m.handle_input(b"0,,EndOfAPI");
        assert_eq!(sent(&mut m), "GroupInitialize(HEXAPOD)");
        m.handle_input(b"0,,EndOfAPI");
        assert_eq!(sent(&mut m), "GroupHomeSearch(HEXAPOD)");
        m.handle_input(b"0,,EndOfAPI");
        assert_eq!(m.poll_outcome(), Some(Ok(Reply::Done)));
        m.start(Command::SetPivot([0.0, 0.0, 120.5]));
        assert_eq!(
            sent(&mut m),
            "HexapodCoordinateSystemSet(HEXAPOD,Tool,0,0,120.5,0,0,0)"
        );
        m.handle_input(b"0,,EndOfAPI");
        assert_eq!(m.poll_outcome(), Some(Ok(Reply::Done)));
        m.start(Command::SetWork(HexPose([1.0, 2.0, 3.0, 0.0, 0.0, 90.0])));
        assert_eq!(
            sent(&mut m),
            "HexapodCoordinateSystemSet(HEXAPOD,Work,1,2,3,0,0,90)"
        );
    }

    /// The speed goes to each actuator's SGamma profile, acceleration and jerk times kept.
    #[test]
    fn speed_sets_every_actuators_sgamma_velocity() {
        let mut m = Xps::new("HEXAPOD");
        m.start(Command::SetSpeed(2.5));
        for n in 1..=6 {
            assert_eq!(
                sent(&mut m),
                format!(
                    "PositionerSGammaParametersGet(HEXAPOD.{n},double *,double *,double *,double *)"
                )
            );
            m.handle_input(b"0,5,20,0.04,0.2,EndOfAPI");
            assert_eq!(
                sent(&mut m),
                format!("PositionerSGammaParametersSet(HEXAPOD.{n},2.5,20,0.04,0.2)")
            );
            assert_eq!(m.poll_outcome(), None);
            m.handle_input(b"0,,EndOfAPI");
        }
        assert_eq!(m.poll_outcome(), Some(Ok(Reply::Done)));
        // A refusal names the controller's code and text.
        m.start(Command::SetSpeed(500.0));
        sent(&mut m);
        m.handle_input(b"0,5,20,0.04,0.2,EndOfAPI");
        sent(&mut m);
        m.handle_input(b"-17,,EndOfAPI");
        assert_eq!(sent(&mut m), "ErrorStringGet(-17,char *)");
        m.handle_input(b"0,Parameter out of range,EndOfAPI");
        assert!(matches!(
            m.poll_outcome(),
            Some(Err(HexapodError::Controller { code: -17, .. }))
        ));
    }

    #[test]
    fn replies_split() {
        assert_eq!(split_reply("0,,EndOfAPI"), Some((0, "")));
        assert_eq!(split_reply("0,EndOfAPI"), Some((0, "")));
        assert_eq!(split_reply("0,12,EndOfAPI"), Some((0, "12")));
        assert_eq!(split_reply("-17,,EndOfAPI"), Some((-17, "")));
        assert_eq!(split_reply("x,EndOfAPI"), None);
        assert_eq!(split_reply("0,12"), None);
    }
}
