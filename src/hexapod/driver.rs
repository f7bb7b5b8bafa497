//! [`Hexapod`]: the thin TCP driver around either protocol machine (DESIGN §11: the machine
//! decides what to send and what an answer means, this owns the socket and the clock).

use super::{Command, Driver, HexPose, HexapodError, Protocol, Reply};
use std::time::Duration;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;
use tokio::time::{Instant, sleep, timeout};

/// How long to wait for the controller.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Timeouts {
    /// Connecting, and any answer of a quick command.
    pub reply: Duration,
    /// A move or the reference move, until in position.
    pub motion: Duration,
    /// Polling interval of the in-position status.
    pub poll: Duration,
}

impl Default for Timeouts {
    fn default() -> Self {
        Timeouts {
            reply: Duration::from_secs(3),
            motion: Duration::from_secs(120),
            poll: Duration::from_millis(20),
        }
    }
}

/// A hexapod controller on a TCP link.
pub struct Hexapod {
    pub kind: Driver,
    pub addr: String,
    pub group: String,
    pub timeouts: Timeouts,
    proto: Box<dyn Protocol>,
    stream: Option<TcpStream>,
}

impl Hexapod {
    /// Connect to the controller of `kind` at `addr` (`host:port`); `group` is the XPS
    /// positioner group (`HEXAPOD`), unused by GCS.
    pub async fn connect(
        kind: Driver,
        addr: &str,
        group: &str,
        timeouts: Timeouts,
    ) -> Result<Hexapod, HexapodError> {
        let mut h = Hexapod {
            kind,
            addr: addr.to_string(),
            group: group.to_string(),
            timeouts,
            proto: kind.machine(group),
            stream: None,
        };
        h.reconnect().await?;
        Ok(h)
    }

    fn link_error(&self, reason: impl Into<String>) -> HexapodError {
        HexapodError::Link {
            controller: self.kind.name(),
            addr: self.addr.clone(),
            reason: reason.into(),
        }
    }

    /// (Re)open the link; a fresh machine forgets any half-answered command.
    pub async fn reconnect(&mut self) -> Result<(), HexapodError> {
        self.stream = None;
        self.proto = self.kind.machine(&self.group);
        let s = timeout(self.timeouts.reply, TcpStream::connect(&self.addr))
            .await
            .map_err(|_| self.link_error("no connection within the reply timeout"))?
            .map_err(|e| self.link_error(e.to_string()))?;
        let _ = s.set_nodelay(true);
        self.stream = Some(s);
        Ok(())
    }

    pub fn connected(&self) -> bool {
        self.stream.is_some()
    }

    /// Run one command to its outcome within `limit`.
    pub async fn exec(&mut self, cmd: Command, limit: Duration) -> Result<Reply, HexapodError> {
        let controller = self.kind.name();
        let Some(stream) = self.stream.as_mut() else {
            return Err(self.link_error("not connected"));
        };
        self.proto.start(cmd);
        let deadline = Instant::now() + limit;
        let mut buf = [0u8; 2048];
        let result = 'io: loop {
            while let Some(bytes) = self.proto.poll_transmit() {
                if let Err(e) = stream.write_all(&bytes).await {
                    break 'io Err(Err(e.to_string()));
                }
            }
            if let Some(outcome) = self.proto.poll_outcome() {
                break Ok(outcome);
            }
            match tokio::time::timeout_at(deadline, stream.read(&mut buf)).await {
                Err(_) => {
                    break Err(Ok(HexapodError::Timeout {
                        controller,
                        command: self.proto.current(),
                        seconds: limit.as_secs_f64(),
                    }));
                }
                Ok(Ok(0)) => break Err(Err("the controller closed the connection".into())),
                Ok(Ok(n)) => self.proto.handle_input(&buf[..n]),
                Ok(Err(e)) => break Err(Err(e.to_string())),
            }
        };
        match result {
            Ok(outcome) => outcome,
            Err(e) => {
                // The link is in an unknown state: a late answer would be taken for the next.
                self.stream = None;
                Err(match e {
                    Ok(timeout) => timeout,
                    Err(reason) => self.link_error(reason),
                })
            }
        }
    }

    /// The controller's identification.
    pub async fn identify(&mut self) -> Result<String, HexapodError> {
        match self.exec(Command::Identify, self.timeouts.reply).await? {
            Reply::Text(t) => Ok(t),
            other => Err(self.unexpected("identify", other)),
        }
    }

    fn unexpected(&self, command: &str, r: Reply) -> HexapodError {
        HexapodError::Protocol {
            controller: self.kind.name(),
            command: command.into(),
            reply: match r {
                Reply::Done => "nothing".into(),
                Reply::Text(t) => t,
                Reply::Pose(p) => format!("a pose ({})", p.0.map(super::wire_number).join(", ")),
                Reply::Flag(b) => b.to_string(),
            },
        }
    }

    async fn flag(&mut self, cmd: Command) -> Result<bool, HexapodError> {
        match self.exec(cmd, self.timeouts.reply).await? {
            Reply::Flag(b) => Ok(b),
            other => Err(self.unexpected(cmd.name(), other)),
        }
    }

    /// Servo on and reference (home), then wait until referenced.
    pub async fn initialize(&mut self) -> Result<(), HexapodError> {
        self.exec(Command::Initialize, self.timeouts.motion).await?;
        self.wait(Command::Referenced).await
    }

    /// Whether the controller says it is referenced and ready.
    pub async fn referenced(&mut self) -> Result<bool, HexapodError> {
        self.flag(Command::Referenced).await
    }

    async fn wait(&mut self, cmd: Command) -> Result<(), HexapodError> {
        let deadline = Instant::now() + self.timeouts.motion;
        loop {
            if self.flag(cmd).await? {
                return Ok(());
            }
            if Instant::now() >= deadline {
                return Err(HexapodError::NotInPosition {
                    controller: self.kind.name(),
                    seconds: self.timeouts.motion.as_secs_f64(),
                });
            }
            sleep(self.timeouts.poll).await;
        }
    }

    /// The pivot point (mm, platform frame) and the work coordinate system.
    pub async fn set_frames(&mut self, pivot: [f64; 3], work: HexPose) -> Result<(), HexapodError> {
        self.exec(Command::SetWork(work), self.timeouts.reply)
            .await?;
        self.exec(Command::SetPivot(pivot), self.timeouts.reply)
            .await?;
        Ok(())
    }

    /// The linear speed (mm/s; 0 keeps the controller's).
    pub async fn set_speed(&mut self, mm_s: f64) -> Result<(), HexapodError> {
        if mm_s > 0.0 {
            self.exec(Command::SetSpeed(mm_s), self.timeouts.reply)
                .await?;
        }
        Ok(())
    }

    /// Move to `p` (work coordinates), wait in position, and read the reached pose.
    pub async fn move_to(&mut self, p: HexPose) -> Result<HexPose, HexapodError> {
        self.exec(Command::Move(p), self.timeouts.motion).await?;
        self.wait(Command::OnTarget).await?;
        self.position().await
    }

    /// The reached pose (work coordinates).
    pub async fn position(&mut self) -> Result<HexPose, HexapodError> {
        match self.exec(Command::Position, self.timeouts.reply).await? {
            Reply::Pose(p) => Ok(p),
            other => Err(self.unexpected("position", other)),
        }
    }

    /// Stop all motion. An XPS call blocks its socket until the move ends, so the abort goes
    /// over a second connection, as Newport's own clients do; GCS takes `STP` on the link.
    pub async fn stop(&mut self) -> Result<(), HexapodError> {
        match self.kind {
            Driver::PiGcs => self
                .exec(Command::Stop, self.timeouts.reply)
                .await
                .map(|_| ()),
            Driver::NewportXps => {
                let mut other =
                    Hexapod::connect(self.kind, &self.addr, &self.group, self.timeouts).await?;
                other
                    .exec(Command::Stop, self.timeouts.reply)
                    .await
                    .map(|_| ())
            }
        }
    }
}
