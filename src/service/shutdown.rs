//! Shutdown fan-out (mini-redis style): one trigger, any number of listeners; every task
//! selects on `recv()` and drains its in-flight work before returning.

use tokio::sync::watch;

/// Fires the shutdown.
#[derive(Debug)]
pub struct Trigger(watch::Sender<bool>);

impl Trigger {
    /// Tell every listener to stop.
    pub fn trigger(&self) {
        let _ = self.0.send(true);
    }
}

/// Listens for the shutdown.
#[derive(Clone, Debug)]
pub struct Shutdown {
    rx: watch::Receiver<bool>,
}

impl Shutdown {
    /// Whether the shutdown has been triggered.
    pub fn is_shutdown(&self) -> bool {
        *self.rx.borrow()
    }

    /// Wait for the shutdown (returns at once when it already happened, or when the trigger is
    /// gone).
    pub async fn recv(&mut self) {
        let _ = self.rx.wait_for(|v| *v).await;
    }
}

/// A connected trigger and listener.
pub fn channel() -> (Trigger, Shutdown) {
    let (tx, rx) = watch::channel(false);
    (Trigger(tx), Shutdown { rx })
}
