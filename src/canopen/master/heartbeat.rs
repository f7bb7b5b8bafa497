//! The heartbeat consumer's events: a boot-up (expected after a reset this master commanded,
//! else the drive rebooted: its configuration is forgotten and a configure under way starts
//! over), the NMT state, loss and resumption; and the time an NMT state change may take.

use super::{Command, DriveError, Event, Master, Step};
use crate::canopen::nmt::HeartbeatEvent;
use std::time::Duration;

impl Master {
    pub(super) fn collect_heartbeat(&mut self) {
        while let Some(ev) = self.hb.poll_event() {
            match ev {
                HeartbeatEvent::BootUp => {
                    self.boot_count += 1;
                    let expected = matches!(
                        self.op.as_ref().and_then(|o| o.steps.front()),
                        Some(Step::AwaitBootUp | Step::Settle(_))
                    );
                    self.events.push_back(Event::BootUp { expected });
                    if !expected {
                        tracing::warn!("follower drive rebooted unexpectedly");
                        self.abort_following(DriveError::Rebooted);
                        self.forget_configuration();
                        if let Some(mut op) = self.op.take() {
                            self.cancel_sdo_of(&op);
                            if op.name == Command::Configure.name() && op.restarts < 2 {
                                // A boot-up during configure (a late power-on boot-up taken
                                // for the reset's, or a drive that restarted): what was
                                // written is gone, so start over on the fresh drive.
                                op.restarts += 1;
                                op.steps = self.plan_configure(false);
                                op.steps
                                    .push_front(Step::Settle(self.s.config().boot_settle));
                                op.started = false;
                                op.deadline = None;
                                self.op = Some(op);
                            } else {
                                self.finish(op, Err(DriveError::Rebooted));
                            }
                        }
                    }
                }
                HeartbeatEvent::State(st) => {
                    self.status.nmt = Some(st);
                    self.events.push_back(Event::Nmt(st));
                }
                HeartbeatEvent::Lost => {
                    tracing::error!("follower drive heartbeat lost");
                    self.events.push_back(Event::HeartbeatLost);
                    self.brake_following(Err(DriveError::HeartbeatLost));
                    let resetting = matches!(
                        self.op.as_ref().and_then(|o| o.steps.front()),
                        Some(Step::AwaitBootUp | Step::Settle(_))
                    );
                    if !resetting && let Some(op) = self.op.take() {
                        self.cancel_sdo_of(&op);
                        self.finish(op, Err(DriveError::HeartbeatLost));
                    }
                }
                HeartbeatEvent::Resumed => self.events.push_back(Event::HeartbeatResumed),
            }
        }
        self.status.heartbeat_ok = self.hb.is_alive();
    }

    pub(super) fn forget_configuration(&mut self) {
        self.abort_following(DriveError::NotConfigured { what: "follow" });
        // Disable voltage until told otherwise: the safe controlword for a drive we lost.
        self.set_cw(0);
        self.status.configured = false;
        self.status.homed = false;
        self.sync.stop();
        self.status.sync_running = false;
    }

    pub(super) fn nmt_timeout(&self) -> Duration {
        let c = self.s.config();
        c.state_timeout.max(c.heartbeat_timeout * 2)
    }
}
