//! The twin drive's tokio task: it owns the transport and the [`TwinDrive`], and takes
//! fault injections from a cloneable [`TwinDriveHandle`] that also watches the status.

use super::{SdoRefusal, TwinDrive, TwinDriveConfig, TwinStatus};
use crate::can::{CanError, CanTransport};
use crate::sim::SimError;
use std::time::Duration;
use tokio::sync::{mpsc, watch};
use tokio::task::JoinHandle;

/// Fault injection and control for a running twin drive.
#[derive(Clone, Debug)]
pub enum TwinControl {
    Fault { code: u16, manufacturer: [u8; 5] },
    Heartbeat(bool),
    RefuseSdo(Option<SdoRefusal>),
    SdoDelay(Duration),
}

/// A handle on a running twin drive.
#[derive(Clone, Debug)]
pub struct TwinDriveHandle {
    control: mpsc::UnboundedSender<TwinControl>,
    status: watch::Receiver<TwinStatus>,
}

impl TwinDriveHandle {
    fn send(&self, c: TwinControl) {
        // A stopped twin ignores injections.
        let _ = self.control.send(c);
    }
    /// Raise a fault with EMCY `code`.
    pub fn inject_fault(&self, code: u16, manufacturer: [u8; 5]) {
        self.send(TwinControl::Fault { code, manufacturer });
    }
    pub fn set_heartbeat(&self, on: bool) {
        self.send(TwinControl::Heartbeat(on));
    }
    pub fn refuse_sdo(&self, refusal: Option<SdoRefusal>) {
        self.send(TwinControl::RefuseSdo(refusal));
    }
    pub fn set_sdo_delay(&self, delay: Duration) {
        self.send(TwinControl::SdoDelay(delay));
    }
    pub fn status(&self) -> TwinStatus {
        self.status.borrow().clone()
    }
    pub fn watch_status(&self) -> watch::Receiver<TwinStatus> {
        self.status.clone()
    }
}

/// Run a twin drive on `transport`, reporting its position to `on_position` (e.g.
/// `move |mm| plant.set_follower_encoder(mm)`). Ends when every handle is dropped or the
/// transport closes.
pub fn spawn_twin_drive<T: CanTransport>(
    transport: T,
    config: TwinDriveConfig,
    on_position: impl FnMut(f64) + Send + 'static,
) -> Result<(TwinDriveHandle, JoinHandle<Result<(), CanError>>), SimError> {
    let d = TwinDrive::new(config, Box::new(on_position), crate::util::clock::now())?;
    let (control, rx) = mpsc::unbounded_channel();
    let (status_tx, status) = watch::channel(d.status());
    let join = tokio::spawn(twin_task(d, transport, rx, status_tx));
    Ok((TwinDriveHandle { control, status }, join))
}

async fn twin_task<T: CanTransport>(
    mut d: TwinDrive,
    bus: T,
    mut control: mpsc::UnboundedReceiver<TwinControl>,
    status: watch::Sender<TwinStatus>,
) -> Result<(), CanError> {
    loop {
        while let Some(f) = d.poll_transmit() {
            match bus.send(&f).await {
                Ok(()) => {}
                Err(CanError::Closed) => return Err(CanError::Closed),
                Err(e) => tracing::warn!("twin drive could not send {f}: {e}"),
            }
        }
        let s = d.status();
        status.send_if_modified(|old| {
            let changed = *old != s;
            *old = s;
            changed
        });
        let deadline = d.poll_timeout();
        tokio::select! {
            r = bus.recv() => match r {
                Ok(f) => d.handle_frame(&f, crate::util::clock::now()),
                Err(e @ (CanError::Lagged(_) | CanError::Malformed(_))) => {
                    tracing::warn!("twin drive: {e}")
                }
                Err(e) => return Err(e),
            },
            c = control.recv() => {
                let now = crate::util::clock::now();
                match c {
                    Some(TwinControl::Fault { code, manufacturer }) => d.inject_fault(code, manufacturer, now),
                    Some(TwinControl::Heartbeat(on)) => d.set_heartbeat(on, now),
                    Some(TwinControl::RefuseSdo(r)) => d.refuse_sdo(r),
                    Some(TwinControl::SdoDelay(t)) => d.set_sdo_delay(t),
                    None => return Ok(()),
                }
            }
            _ = async {
                match deadline {
                    Some(t) => tokio::time::sleep_until(tokio::time::Instant::from_std(t)).await,
                    None => std::future::pending().await,
                }
            } => d.handle_timeout(crate::util::clock::now()),
        }
    }
}
