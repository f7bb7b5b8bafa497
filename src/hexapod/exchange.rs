//! What both protocol machines share: a queue of requests, each with what its answer must be,
//! the one awaiting its answer, the bytes to send, the input so far and the outcome.

use super::{Command, HexapodError, Reply};
use std::collections::VecDeque;

#[derive(Debug)]
pub(crate) struct Exchange<E> {
    pub cmd: Option<Command>,
    steps: VecDeque<(String, E)>,
    pub current: Option<(String, E)>,
    out: VecDeque<Vec<u8>>,
    pub buf: Vec<u8>,
    pub outcome: Option<Result<Reply, HexapodError>>,
}

impl<E: Clone> Exchange<E> {
    pub fn new() -> Self {
        Exchange {
            cmd: None,
            steps: VecDeque::new(),
            current: None,
            out: VecDeque::new(),
            buf: Vec::new(),
            outcome: None,
        }
    }

    /// Begin `cmd` with its requests; a command still running is dropped.
    pub fn start(&mut self, cmd: Command, steps: Vec<(String, E)>) {
        self.cmd = Some(cmd);
        self.steps = steps.into();
        self.buf.clear();
        self.out.clear();
        self.outcome = None;
        self.next();
    }

    /// Send the next request, or end the command (`Done` unless an answer set the outcome).
    pub fn next(&mut self) {
        match self.steps.pop_front() {
            Some(s) => {
                self.out.push_back(s.0.clone().into_bytes());
                self.current = Some(s);
            }
            None => {
                self.current = None;
                if self.outcome.is_none() {
                    self.outcome = Some(Ok(Reply::Done));
                }
            }
        }
    }

    /// Replace the remaining requests with `step` and send it.
    pub fn instead(&mut self, step: (String, E)) {
        self.steps.clear();
        self.steps.push_back(step);
        self.next();
    }

    /// Send `step` next, before the remaining requests (a request built from an answer).
    pub fn then(&mut self, step: (String, E)) {
        self.steps.push_front(step);
        self.next();
    }

    pub fn fail(&mut self, e: HexapodError) {
        self.steps.clear();
        self.current = None;
        self.outcome = Some(Err(e));
    }

    pub fn poll_transmit(&mut self) -> Option<Vec<u8>> {
        self.out.pop_front()
    }

    pub fn poll_outcome(&mut self) -> Option<Result<Reply, HexapodError>> {
        if self.current.is_some() {
            return None;
        }
        self.outcome.take()
    }

    /// The request awaiting its answer, as sent (trailing line ends removed).
    pub fn request(&self) -> Option<&str> {
        self.current.as_ref().map(|s| s.0.trim_end())
    }
}
