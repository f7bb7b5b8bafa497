//! NMT master side (CiA 301 §7.2.8): node-control commands and the heartbeat consumer.
//!
//! Commands go out on COB-ID 0x000 as `[command specifier, node id]` (canopen-rs's codec).
//! The drive's error-control frames arrive on 0x700 + node with one byte: 0x00 is the boot-up
//! message (the node has just entered pre-operational), otherwise its NMT state (0x04 stopped,
//! 0x05 operational, 0x7F pre-operational; bit 7 is the node-guarding toggle and ignored).
//!
//! The consumer starts watching at the first heartbeat (CiA 301: a consumer is active once it
//! has heard the producer) and reports the loss once when nothing is heard for the consumer
//! time, then the resumption when heartbeats return. A boot-up message disarms it until the
//! next heartbeat: after a reset the producer time is back at its default (often 0, no
//! heartbeat) until the master writes 0x1017 again.

use super::{cob, frame};
use crate::can::CanFrame;
use canopen_rs::nmt::encode_command;
use canopen_rs::{NmtCommand, NmtState, NodeId};
use std::collections::VecDeque;
use std::time::{Duration, Instant};

/// The NMT node-control frame sending `cmd` to `node`.
pub fn command_frame(cmd: NmtCommand, node: NodeId) -> CanFrame {
    frame(cob::NMT, &encode_command(cmd, node))
}

/// An NMT state's name as CiA 301 writes it: "Initialising", "Pre-operational",
/// "Operational", "Stopped".
pub fn state_name(s: NmtState) -> &'static str {
    match s {
        NmtState::Initialising => "Initialising",
        NmtState::PreOperational => "Pre-operational",
        NmtState::Operational => "Operational",
        NmtState::Stopped => "Stopped",
    }
}

/// What the consumer noticed.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum HeartbeatEvent {
    /// A boot-up message: the node (re)started and is now pre-operational.
    BootUp,
    /// The reported NMT state changed (first report included).
    State(NmtState),
    /// Nothing heard for the consumer time.
    Lost,
    /// Heard again after a loss.
    Resumed,
}

/// The heartbeat consumer for one node.
#[derive(Debug)]
pub struct HeartbeatConsumer {
    node: NodeId,
    timeout: Duration,
    last: Option<Instant>,
    armed: bool,
    state: Option<NmtState>,
    lost: bool,
    events: VecDeque<HeartbeatEvent>,
}

impl HeartbeatConsumer {
    /// Watch `node`, declaring it lost after `timeout` (the consumer heartbeat time).
    pub fn new(node: NodeId, timeout: Duration) -> Self {
        HeartbeatConsumer {
            node,
            timeout,
            last: None,
            armed: false,
            state: None,
            lost: false,
            events: VecDeque::new(),
        }
    }

    /// The last reported NMT state.
    pub fn state(&self) -> Option<NmtState> {
        self.state
    }

    /// Whether heartbeats are arriving (false before the first one, after a boot-up until
    /// the next one, and while lost).
    pub fn is_alive(&self) -> bool {
        self.armed && !self.lost
    }

    /// When the last heartbeat or boot-up arrived.
    pub fn last_heard(&self) -> Option<Instant> {
        self.last
    }

    /// Feed a frame; returns whether it was this node's error-control frame.
    pub fn handle_frame(&mut self, f: &CanFrame, now: Instant) -> bool {
        if f.is_extended() || f.id() != (cob::HEARTBEAT + self.node.raw() as u16) as u32 {
            return false;
        }
        // A remote frame here is a node-guarding request from someone else: not a heartbeat.
        if f.is_remote() || f.len() != 1 {
            return true;
        }
        let byte = f.data()[0];
        self.last = Some(now);
        if self.lost {
            self.lost = false;
            self.events.push_back(HeartbeatEvent::Resumed);
        }
        let state = if byte & 0x7F == 0 {
            self.armed = false;
            self.events.push_back(HeartbeatEvent::BootUp);
            NmtState::PreOperational
        } else {
            self.armed = true;
            match NmtState::from_wire(byte) {
                Ok(s) => s,
                // A reserved state value: the node is alive, its state unknown.
                Err(_) => return true,
            }
        };
        if self.state != Some(state) {
            self.state = Some(state);
            self.events.push_back(HeartbeatEvent::State(state));
        }
        true
    }

    /// Feed the clock: report the loss once when the consumer time has passed.
    pub fn handle_timeout(&mut self, now: Instant) {
        if let Some(deadline) = self.poll_timeout()
            && now >= deadline
        {
            self.lost = true;
            self.events.push_back(HeartbeatEvent::Lost);
        }
    }

    /// When the node will be declared lost if nothing arrives.
    pub fn poll_timeout(&self) -> Option<Instant> {
        match self.last {
            Some(t) if self.armed && !self.lost => Some(t + self.timeout),
            _ => None,
        }
    }

    pub fn poll_event(&mut self) -> Option<HeartbeatEvent> {
        self.events.pop_front()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn hb(node: u8, byte: u8) -> CanFrame {
        CanFrame::new(0x700 + node as u16, &[byte]).unwrap()
    }

    #[test]
    fn command_frames() {
        let n = NodeId::new(5).unwrap();
        let f = command_frame(NmtCommand::StartRemoteNode, n);
        assert_eq!(format!("{f:?}"), "000#0105");
        assert_eq!(
            format!("{:?}", command_frame(NmtCommand::StopRemoteNode, n)),
            "000#0205"
        );
        assert_eq!(
            format!("{:?}", command_frame(NmtCommand::EnterPreOperational, n)),
            "000#8005"
        );
        assert_eq!(
            format!("{:?}", command_frame(NmtCommand::ResetNode, n)),
            "000#8105"
        );
        assert_eq!(
            format!("{:?}", command_frame(NmtCommand::ResetCommunication, n)),
            "000#8205"
        );
    }

    #[test]
    fn boot_up_state_loss_and_resumption() {
        let t0 = crate::util::clock::now();
        let ms = |n: u64| t0 + Duration::from_millis(n);
        let mut c = HeartbeatConsumer::new(NodeId::new(1).unwrap(), Duration::from_millis(300));
        // Not watching before the first frame.
        assert_eq!(c.poll_timeout(), None);
        assert!(!c.is_alive());
        // Other nodes' heartbeats are not ours.
        assert!(!c.handle_frame(&hb(2, 0x05), t0));
        assert!(c.handle_frame(&hb(1, 0x00), t0));
        assert_eq!(c.poll_event(), Some(HeartbeatEvent::BootUp));
        assert_eq!(
            c.poll_event(),
            Some(HeartbeatEvent::State(NmtState::PreOperational))
        );
        assert_eq!(c.poll_event(), None);
        // A boot-up alone does not arm the consumer (the producer time may be 0).
        assert_eq!(c.poll_timeout(), None);
        assert!(!c.is_alive());
        c.handle_frame(&hb(1, 0x7F), ms(100));
        assert_eq!(c.poll_event(), None);
        assert_eq!(c.poll_timeout(), Some(ms(400)));
        c.handle_frame(&hb(1, 0x05), ms(200));
        assert_eq!(
            c.poll_event(),
            Some(HeartbeatEvent::State(NmtState::Operational))
        );
        // Toggle bit 7 is ignored.
        c.handle_frame(&hb(1, 0x85), ms(300));
        assert_eq!(c.poll_event(), None);
        assert_eq!(c.poll_timeout(), Some(ms(600)));
        c.handle_timeout(ms(599));
        assert_eq!(c.poll_event(), None);
        assert!(c.is_alive());
        c.handle_timeout(ms(600));
        assert_eq!(c.poll_event(), Some(HeartbeatEvent::Lost));
        assert!(!c.is_alive());
        // Reported once only.
        assert_eq!(c.poll_timeout(), None);
        c.handle_timeout(ms(5000));
        assert_eq!(c.poll_event(), None);
        c.handle_frame(&hb(1, 0x04), ms(6000));
        assert_eq!(c.poll_event(), Some(HeartbeatEvent::Resumed));
        assert_eq!(
            c.poll_event(),
            Some(HeartbeatEvent::State(NmtState::Stopped))
        );
        assert_eq!(c.state(), Some(NmtState::Stopped));
        // Reserved state values keep the node alive without a state change.
        c.handle_frame(&hb(1, 0x33), ms(6100));
        assert_eq!(c.poll_event(), None);
        assert_eq!(c.poll_timeout(), Some(ms(6400)));
    }
}
