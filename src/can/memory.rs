//! An in-process CAN bus: every port sees the frames of every other port, in order, as on a
//! real bus. For unit tests and the in-process twin.

use super::{CanError, CanFrame, CanTransport};
use std::sync::atomic::{AtomicU64, Ordering};
use tokio::sync::{Mutex, broadcast};

/// The bus; clone it to share, call `port` to attach a node.
#[derive(Clone, Debug)]
pub struct MemoryBus {
    tx: broadcast::Sender<(u64, CanFrame)>,
}

static NEXT_PORT: AtomicU64 = AtomicU64::new(1);

impl MemoryBus {
    /// A bus that buffers up to `capacity` frames per slow reader before it overruns.
    pub fn new(capacity: usize) -> Self {
        let (tx, _) = broadcast::channel(capacity.max(16));
        MemoryBus { tx }
    }

    /// Attach a new node.
    pub fn port(&self) -> MemoryPort {
        MemoryPort {
            id: NEXT_PORT.fetch_add(1, Ordering::Relaxed),
            tx: self.tx.clone(),
            rx: Mutex::new(self.tx.subscribe()),
        }
    }
}

impl Default for MemoryBus {
    fn default() -> Self {
        MemoryBus::new(4096)
    }
}

/// One node's attachment to a `MemoryBus`.
#[derive(Debug)]
pub struct MemoryPort {
    id: u64,
    tx: broadcast::Sender<(u64, CanFrame)>,
    rx: Mutex<broadcast::Receiver<(u64, CanFrame)>>,
}

impl CanTransport for MemoryPort {
    async fn send(&self, frame: &CanFrame) -> Result<(), CanError> {
        // No receivers is not an error on a bus: the frame is simply not heard.
        let _ = self.tx.send((self.id, *frame));
        Ok(())
    }

    async fn recv(&self) -> Result<CanFrame, CanError> {
        let mut rx = self.rx.lock().await;
        loop {
            match rx.recv().await {
                Ok((from, f)) if from != self.id => return Ok(f),
                Ok(_) => continue,
                Err(broadcast::error::RecvError::Lagged(n)) => return Err(CanError::Lagged(n)),
                Err(broadcast::error::RecvError::Closed) => return Err(CanError::Closed),
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn ports_hear_each_other_not_themselves() {
        let bus = MemoryBus::default();
        let a = bus.port();
        let b = bus.port();
        let c = bus.port();
        a.send(&CanFrame::new(0x100, &[1]).unwrap()).await.unwrap();
        b.send(&CanFrame::new(0x200, &[2]).unwrap()).await.unwrap();
        assert_eq!(b.recv().await.unwrap().id(), 0x100);
        assert_eq!(a.recv().await.unwrap().id(), 0x200);
        assert_eq!(c.recv().await.unwrap().id(), 0x100);
        assert_eq!(c.recv().await.unwrap().id(), 0x200);
    }

    #[tokio::test]
    async fn overrun_is_reported() {
        let bus = MemoryBus::new(16);
        let a = bus.port();
        let b = bus.port();
        for i in 0..40u16 {
            a.send(&CanFrame::new(i, &[]).unwrap()).await.unwrap();
        }
        assert!(matches!(b.recv().await, Err(CanError::Lagged(_))));
        assert!(b.recv().await.is_ok());
    }
}
