//! The one CNC program driver of the service's procedures (the measurement run, the
//! follower's mapping and level stations): a part program written to the state directory and,
//! with `[cnc] mode = "twin"`, sent to the twin's CNC; the twin's CNC watched (once a second
//! while a program of ours may run) until the program we sent has ended; a stop at its next
//! stop. With a CNC the service does not drive, the operator loads the file, and the
//! procedure judges the end by what the carriage did.
//!
//! Sans-I/O on the procedure's side: `deliver`, `stop` and `poll` start small tasks (the
//! twin's control socket is TCP), their news comes back on a bounded channel and is taken in
//! `poll`, which every procedure calls from its tick with the time.

use super::procedure::Reply;
use crate::config::CncMode;
use crate::run::Dialect;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};
use tokio::sync::mpsc;

/// How often the twin's CNC is asked for its state while a program of ours may run.
const POLL_EVERY: Duration = Duration::from_secs(1);

/// Send one JSON request to the twin's control socket and read its reply (5 s for each).
pub async fn twin_request(
    addr: SocketAddr,
    req: serde_json::Value,
) -> Result<serde_json::Value, String> {
    use tokio::io::{AsyncBufReadExt, AsyncWriteExt, BufReader};
    let s = tokio::time::timeout(Duration::from_secs(5), tokio::net::TcpStream::connect(addr))
        .await
        .map_err(|_| format!("twin CNC {addr}: no connection within 5 s"))?
        .map_err(|e| format!("twin CNC {addr}: {e}"))?;
    let (rd, mut wr) = s.into_split();
    let mut line = req.to_string();
    line.push('\n');
    wr.write_all(line.as_bytes())
        .await
        .map_err(|e| format!("twin CNC {addr}: {e}"))?;
    let mut lines = BufReader::new(rd).lines();
    let reply = tokio::time::timeout(Duration::from_secs(5), lines.next_line())
        .await
        .map_err(|_| format!("twin CNC {addr}: no reply within 5 s"))?
        .map_err(|e| format!("twin CNC {addr}: {e}"))?
        .ok_or_else(|| format!("twin CNC {addr}: closed"))?;
    let v: serde_json::Value =
        serde_json::from_str(&reply).map_err(|e| format!("twin CNC {addr}: {e}"))?;
    if v.get("ok").and_then(|o| o.as_bool()) == Some(true) {
        Ok(v)
    } else {
        Err(format!(
            "twin CNC {addr}: {}",
            v.get("error").and_then(|e| e.as_str()).unwrap_or("refused")
        ))
    }
}

/// The twin's CNC as one poll saw it.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct CncState {
    /// The last program has ended.
    pub done: bool,
    /// Programs started so far (the twin counts them).
    pub programs: u32,
    /// The target code of the stop it is at or last was at (the program's position), 0
    /// before the first.
    pub code: u32,
}

impl CncState {
    fn of(v: &serde_json::Value) -> CncState {
        let n = |k: &str| v["cnc"][k].as_u64().and_then(|x| u32::try_from(x).ok());
        CncState {
            done: v["cnc"]["done"].as_bool().unwrap_or(false),
            programs: n("programs").unwrap_or(0),
            code: n("code").unwrap_or(0),
        }
    }
}

/// What the driver heard.
#[derive(Clone, Debug, PartialEq)]
pub enum CncNews {
    /// The twin did not take the program: the procedure cannot go on with it.
    Refused(String),
    /// The program we sent has ended (the twin's CNC is done with it).
    Ended,
    /// The program we sent is written (and taken by the twin when it drives it).
    Taken,
}

#[derive(Debug)]
enum Heard {
    /// The program written (and taken by the twin: its program count after).
    Delivered(Result<Option<u32>, String>),
    State(CncState),
}

/// One procedure's CNC programs.
#[derive(Debug)]
pub struct CncDriver {
    mode: CncMode,
    tx: mpsc::Sender<Heard>,
    rx: mpsc::Receiver<Heard>,
    /// The twin's program count once our latest program was taken (its number there).
    ours: Option<u32>,
    /// A program of ours was sent and has not been seen to end.
    running: bool,
    last_poll: Option<Instant>,
    /// The last state seen.
    pub state: Option<CncState>,
}

impl CncDriver {
    pub fn new(mode: CncMode) -> CncDriver {
        let (tx, rx) = mpsc::channel(16);
        CncDriver {
            mode,
            tx,
            rx,
            ours: None,
            running: false,
            last_poll: None,
            state: None,
        }
    }

    /// The twin's control socket, when the service drives the twin's CNC.
    pub fn twin(&self) -> Option<SocketAddr> {
        match self.mode {
            CncMode::Twin(a) => Some(a),
            CncMode::Manual => None,
        }
    }

    /// Whether a program of ours was sent and has not ended.
    pub fn running(&self) -> bool {
        self.running
    }

    /// Where program `name` goes in `dir` (`name.<ext>`) and what becomes of it, in words;
    /// refused when the twin's CNC cannot run the dialect.
    pub fn program_file(
        &self,
        dir: &Path,
        name: &str,
        dialect: Dialect,
    ) -> Result<(PathBuf, String), String> {
        let file = dir.join(format!("{name}.{}", dialect.extension()));
        match self.twin() {
            Some(_) if !matches!(dialect, Dialect::Iso | Dialect::LinuxCnc) => {
                Err("the twin's CNC runs iso or linuxcnc programs".into())
            }
            Some(addr) => Ok((file, format!("sent to the twin's CNC at {addr}"))),
            None => Ok((file, "load the program on the CNC and start it".into())),
        }
    }

    /// Write `text` as `file` (from [`program_file`](Self::program_file)) and, with the
    /// twin's CNC, send it (replacing a program that runs there), off the loop. A file that
    /// cannot be written, or a twin that does not take the program, is news (`Refused`) at
    /// the next poll. `then`, a reply owed and its answer, is answered once the file is
    /// written and the twin has the program (or with why not).
    pub fn deliver(
        &mut self,
        file: PathBuf,
        text: String,
        dialect: Dialect,
        axis: &str,
        then: Option<(Reply, serde_json::Value)>,
    ) {
        let twin = self.twin();
        self.ours = None;
        self.running = true;
        let (tx, path, axis) = (self.tx.clone(), file, axis.to_string());
        tokio::spawn(async move {
            let written = {
                let (path, text) = (path.clone(), text.clone());
                tokio::task::spawn_blocking(move || {
                    if let Some(dir) = path.parent() {
                        std::fs::create_dir_all(dir)?;
                    }
                    std::fs::write(&path, text)
                })
                .await
            };
            let r = match written {
                Ok(Ok(())) => match twin {
                    Some(addr) => {
                        let req = serde_json::json!({
                            "cmd": "program",
                            "dialect": if dialect == Dialect::LinuxCnc { "linuxcnc" } else { "iso" },
                            "axis": axis,
                            "text": text,
                        });
                        match twin_request(addr, req).await {
                            Ok(_) => twin_request(addr, serde_json::json!({"cmd": "cnc"}))
                                .await
                                .map(|v| Some(CncState::of(&v).programs)),
                            Err(e) => Err(e),
                        }
                    }
                    None => Ok(None),
                },
                Ok(Err(e)) => Err(format!("cannot write the program {}: {e}", path.display())),
                Err(e) => Err(format!("cannot write the program {}: {e}", path.display())),
            };
            if let Some((reply, answer)) = then {
                reply.send(match &r {
                    Ok(_) => Ok(answer),
                    Err(e) => Err(e.clone()),
                });
            }
            let _ = tx.send(Heard::Delivered(r)).await;
        });
    }

    /// Stop the twin's program at its next stop (the move in progress ends).
    pub fn stop(&mut self) {
        let Some(addr) = self.twin() else {
            return;
        };
        tokio::spawn(async move {
            if let Err(e) =
                twin_request(addr, serde_json::json!({"cmd": "cnc", "stop": true})).await
            {
                tracing::warn!("the twin's CNC was not stopped: {e}");
            }
        });
    }

    /// Forget the program sent (its end no longer matters).
    pub fn forget(&mut self) {
        self.running = false;
        self.ours = None;
    }

    /// Take the news (and ask the twin's CNC for its state once a second while a program of
    /// ours may run).
    pub fn poll(&mut self, now: Instant) -> Vec<CncNews> {
        let mut news = Vec::new();
        while let Ok(h) = self.rx.try_recv() {
            match h {
                Heard::Delivered(Ok(Some(n))) => {
                    self.ours = Some(n);
                    news.push(CncNews::Taken);
                }
                // Written for the operator: its end is judged by the carriage.
                Heard::Delivered(Ok(None)) => {
                    self.running = false;
                    news.push(CncNews::Taken);
                }
                Heard::Delivered(Err(e)) => {
                    self.running = false;
                    news.push(CncNews::Refused(e));
                }
                Heard::State(st) => {
                    self.state = Some(st);
                    if self.running && st.done && self.ours == Some(st.programs) {
                        self.running = false;
                        news.push(CncNews::Ended);
                    }
                }
            }
        }
        if let Some(addr) = self.twin()
            && self.running
            && self
                .last_poll
                .is_none_or(|t| now.saturating_duration_since(t) >= POLL_EVERY)
        {
            self.last_poll = Some(now);
            let tx = self.tx.clone();
            tokio::spawn(async move {
                if let Ok(v) = twin_request(addr, serde_json::json!({"cmd": "cnc"})).await {
                    let _ = tx.send(Heard::State(CncState::of(&v))).await;
                }
            });
        }
        news
    }
}
