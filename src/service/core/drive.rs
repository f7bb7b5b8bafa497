//! The core and the follower drive: the tracker's targets to the drive (the latest only),
//! the drive brought up (configured, started, enabled, homed) and again after a reboot, the
//! operator's follower commands, a quick stop for a lost heartbeat and the enable after it.
//! Drive commands go out as small tasks of their own: the loop never waits on the bus.

use super::{Core, CoreEvent};
use crate::canopen::{DriveError, DriveHandle, Event};
use crate::service::api::FollowerAction;
use crate::service::procedure::{Reply, Who};
use crate::service::shutdown::Shutdown;
use crate::track::FollowerCommand;
use std::time::Duration;
use tokio::sync::{broadcast, watch};

impl Core {
    /// A follower command of the tracker's.
    pub(super) fn follower_output(&mut self, cmd: FollowerCommand) {
        match cmd {
            // Only the latest target matters: the follower task skips superseded ones.
            FollowerCommand::MoveTo(mm) => {
                self.follow.send_replace(Some(mm));
            }
            FollowerCommand::Follow {
                target_mm,
                velocity_mm_s,
                at,
            } => {
                if self.csp_refused || std::mem::take(&mut self.follow_rearm) {
                    self.follow.send_replace(Some(target_mm));
                    return;
                }
                match self.drive.follow_moving(target_mm, velocity_mm_s, at) {
                    Ok(()) => {}
                    // Following ended (a stop, a fault, a drive refusing mode 8): go on in
                    // profile position; the move re-arms following.
                    Err(DriveError::FollowDisarmed) => {
                        self.follow.send_replace(Some(target_mm));
                    }
                    Err(e) => tracing::warn!("follower to {target_mm:.4} mm: {e}"),
                }
            }
        }
    }

    /// Stop the follower now (its heartbeat is lost).
    pub(super) fn quick_stop(&self) {
        let drive = self.drive.clone();
        tokio::spawn(async move {
            let _ = drive.quick_stop().await;
        });
    }

    /// Enable the follower again after its heartbeat came back.
    pub(super) fn re_enable(&self) {
        let drive = self.drive.clone();
        let tx = self.events_tx.clone();
        tokio::spawn(async move {
            // Quick stop leaves the drive in switch on disabled; a drive that faulted
            // meanwhile needs its fault reset first.
            let r = match drive.enable().await {
                Ok(()) => Ok(()),
                Err(_) => match drive.fault_reset().await {
                    Ok(()) => drive.enable().await,
                    Err(e) => Err(e),
                },
            };
            let _ = tx
                .send(CoreEvent::ReEnabled(r.map_err(|e| e.to_string())))
                .await;
        });
    }

    /// A drive that refuses cyclic synchronous position (an SDO abort on entering it) is
    /// followed in profile position until it reboots.
    pub(super) fn note_following(&mut self, e: &Event) {
        match e {
            Event::FollowingEnded(Err(DriveError::Sdo(err))) => {
                if !self.csp_refused {
                    tracing::warn!(
                        "the follower drive refused cyclic synchronous position ({err}): \
                         following in profile position, which lags a moving carriage"
                    );
                }
                self.csp_refused = true;
            }
            // Following ended on an error (a following error, a stop): the next target goes
            // as a profile move, which re-arms following.
            Event::FollowingEnded(Err(_)) => self.follow_rearm = true,
            Event::BootUp { .. } => self.csp_refused = false,
            _ => {}
        }
    }

    /// The operator's `follower` request: carried out on a task of its own, answered when
    /// the drive has.
    pub(super) fn follower_request(
        &mut self,
        action: FollowerAction,
        mm: Option<f64>,
        who: &Who,
        reply: Reply,
    ) {
        if matches!(
            action,
            FollowerAction::Jog | FollowerAction::Move | FollowerAction::Home
        ) {
            if mm.is_none() && action != FollowerAction::Home {
                return reply.send(Err("jog and move need \"mm\"".into()));
            }
            // A commanded move is not a measured handover: the stitch must be re-zeroed.
            // Said as what it was (a jog, a move, a homing) and by whom.
            let what = match action {
                FollowerAction::Jog => "jogged",
                FollowerAction::Move => "moved to a position",
                _ => "homed",
            };
            self.pipeline.invalidate_stitch(&format!(
                "the follower was {what} by {}'s request: zero again before measuring",
                who.user
            ));
        }
        let drive = self.drive.clone();
        tokio::spawn(async move {
            let r = match (action, mm) {
                (FollowerAction::Home, _) => drive.home().await,
                (FollowerAction::Enable, _) => drive.enable().await,
                (FollowerAction::Disable, _) => drive.disable().await,
                (FollowerAction::Stop, _) => drive.stop().await,
                (FollowerAction::FaultReset, _) => match drive.fault_reset().await {
                    Ok(()) => drive.enable().await,
                    Err(e) => Err(e),
                },
                (FollowerAction::Jog, Some(d)) => drive.jog(d).await,
                (FollowerAction::Move, Some(t)) => drive.move_to(t).await,
                (FollowerAction::Jog | FollowerAction::Move, None) => {
                    return reply.send(Err("jog and move need \"mm\"".into()));
                }
            };
            reply.send(
                r.map(|()| serde_json::json!({"position_mm": drive.status().position_mm}))
                    .map_err(|e| format!("follower {}: {e}", action_name(action))),
            );
        });
    }
}

/// The action in words.
fn action_name(a: FollowerAction) -> &'static str {
    match a {
        FollowerAction::Home => "home",
        FollowerAction::Enable => "enable",
        FollowerAction::Disable => "disable",
        FollowerAction::Jog => "jog",
        FollowerAction::Move => "move",
        FollowerAction::Stop => "stop",
        FollowerAction::FaultReset => "fault reset",
    }
}

/// Send the tracker's follower targets, always the latest: a set-point takes a couple of SYNC
/// periods, and targets that were superseded meanwhile are never sent.
pub(super) async fn follow(
    drive: DriveHandle,
    mut targets: watch::Receiver<Option<f64>>,
    mut shutdown: Shutdown,
) {
    loop {
        tokio::select! {
            _ = shutdown.recv() => return,
            r = targets.changed() => {
                if r.is_err() {
                    return;
                }
                let target = *targets.borrow_and_update();
                if let Some(mm) = target
                    && let Err(e) = drive.set_target(mm).await
                {
                    tracing::warn!("follower to {mm:.4} mm: {e}");
                }
            }
        }
    }
}

/// Bring the drive up: configure its PDOs, start it, enable it (and home it when asked),
/// retrying while it is unreachable; again whenever it reboots.
pub(super) async fn bring_up(drive: DriveHandle, home: bool, mut shutdown: Shutdown) {
    let mut events = drive.events();
    loop {
        let attempt = async {
            drive.configure().await?;
            drive.start().await?;
            drive.enable().await?;
            if home || !drive.status().homed {
                drive.home().await?;
            }
            Ok::<(), crate::canopen::DriveError>(())
        };
        let r = tokio::select! {
            _ = shutdown.recv() => return,
            r = attempt => r,
        };
        match r {
            Ok(()) => {
                tracing::info!("follower drive configured, enabled and homed");
                // Wait for a reboot, then do it again.
                loop {
                    tokio::select! {
                        _ = shutdown.recv() => return,
                        e = events.recv() => match e {
                            Ok(Event::BootUp { expected: false }) => break,
                            Ok(_) | Err(broadcast::error::RecvError::Lagged(_)) => {}
                            Err(broadcast::error::RecvError::Closed) => return,
                        },
                    }
                }
            }
            Err(e) => {
                tracing::warn!("follower drive bring-up failed: {e}; retrying in 2 s");
                tokio::select! {
                    _ = shutdown.recv() => return,
                    _ = tokio::time::sleep(Duration::from_secs(2)) => {}
                }
            }
        }
    }
}
