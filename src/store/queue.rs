//! The store behind a bounded queue (DESIGN §5, "Time and the disk"): the service's event
//! loop never waits for the disk. A [`StoreQueue`] owns the one read-write connection; jobs
//! (closures over the [`Store`]) run one at a time, in the order they were queued, on a
//! blocking thread, and their results come back on a oneshot. A store locked by another
//! process for its busy timeout, an fsync on a slow card or a full disk holds up the queue,
//! never the loop.
//!
//! Two ways in: [`StoreQueue::call`] waits for room in the queue and then for the result (for
//! tasks that may wait); [`StoreQueue::try_call`] queues at once or says the queue is full,
//! and hands back a future of the result (for the event loop, which must not wait even for
//! room: a full queue is a store that cannot keep up, and the caller raises the store alarm
//! and keeps what it could not queue).
//!
//! On a paused test clock, tokio does not advance the clock while a blocking job runs: a
//! job takes no simulated time.

use super::Store;
use std::future::Future;
use thiserror::Error;
use tokio::sync::{mpsc, oneshot};

/// Jobs waiting at most (beyond this the queue is full).
pub const DEPTH: usize = 256;

type Job = Box<dyn FnOnce(&mut Store) + Send>;

/// Why a job did not run.
#[derive(Clone, Copy, Debug, Error, PartialEq, Eq)]
pub enum QueueError {
    #[error("the store's queue is full ({DEPTH} jobs waiting): the disk does not keep up")]
    Full,
    #[error("the store's thread has ended (the service is stopping, or it failed)")]
    Gone,
}

/// The queue's sending side: cheap to clone, one per task that uses the store.
#[derive(Clone, Debug)]
pub struct StoreQueue {
    tx: mpsc::Sender<Job>,
}

impl StoreQueue {
    /// Serve `store` from a task of its own on the current runtime; the task ends when every
    /// handle is dropped (after the jobs queued so far).
    pub fn spawn(store: Store) -> (StoreQueue, tokio::task::JoinHandle<()>) {
        let (tx, rx) = mpsc::channel(DEPTH);
        (StoreQueue { tx }, tokio::spawn(serve(store, rx)))
    }

    /// Run `f` on the store: wait for room in the queue, then for its result.
    pub async fn call<R, F>(&self, f: F) -> Result<R, QueueError>
    where
        R: Send + 'static,
        F: FnOnce(&mut Store) -> R + Send + 'static,
    {
        let (done, result) = oneshot::channel();
        let job: Job = Box::new(move |s| {
            let _ = done.send(f(s));
        });
        self.tx.send(job).await.map_err(|_| QueueError::Gone)?;
        result.await.map_err(|_| QueueError::Gone)
    }

    /// Queue `f` now, without waiting; its result as a future. `Full` when the queue is full
    /// (nothing queued).
    pub fn try_call<R, F>(
        &self,
        f: F,
    ) -> Result<impl Future<Output = Result<R, QueueError>> + Send + 'static, QueueError>
    where
        R: Send + 'static,
        F: FnOnce(&mut Store) -> R + Send + 'static,
    {
        let (done, result) = oneshot::channel();
        let job: Job = Box::new(move |s| {
            let _ = done.send(f(s));
        });
        self.tx.try_send(job).map_err(|e| match e {
            mpsc::error::TrySendError::Full(_) => QueueError::Full,
            mpsc::error::TrySendError::Closed(_) => QueueError::Gone,
        })?;
        Ok(async move { result.await.map_err(|_| QueueError::Gone) })
    }
}

/// Take the jobs queued so far and run them, in order, on a blocking thread; again.
async fn serve(store: Store, mut rx: mpsc::Receiver<Job>) {
    let mut store = Some(store);
    let mut batch: Vec<Job> = Vec::new();
    while rx.recv_many(&mut batch, DEPTH).await > 0 {
        let Some(mut s) = store.take() else {
            return;
        };
        let jobs = std::mem::take(&mut batch);
        match tokio::task::spawn_blocking(move || {
            for job in jobs {
                job(&mut s);
            }
            s
        })
        .await
        {
            Ok(s) => store = Some(s),
            Err(e) => {
                // A job panicked: the connection went with it; the handles get `Gone`.
                tracing::error!("the store's thread failed: {e}");
                return;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    fn temp_store(name: &str) -> (Store, std::path::PathBuf) {
        let dir = std::env::temp_dir().join(format!(
            "axiscomp-queue-{name}-{}-{:?}",
            std::process::id(),
            std::thread::current().id()
        ));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).expect("temp dir");
        let path = dir.join("q.db");
        (Store::open(&path).expect("store"), dir)
    }

    /// Jobs run in the order queued, and each gives its own result back.
    #[tokio::test]
    async fn jobs_run_in_order_and_answer() {
        let (store, dir) = temp_store("order");
        let (q, task) = StoreQueue::spawn(store);
        let order = std::sync::Arc::new(std::sync::Mutex::new(Vec::new()));
        let mut pending = Vec::new();
        for k in 0..20 {
            let o = order.clone();
            pending.push(
                q.try_call(move |_| {
                    o.lock().expect("order").push(k);
                    k * 2
                })
                .expect("room"),
            );
        }
        for (k, p) in pending.into_iter().enumerate() {
            assert_eq!(p.await, Ok(k * 2));
        }
        assert_eq!(*order.lock().expect("order"), (0..20).collect::<Vec<_>>());
        assert_eq!(q.call(|s| s.schema_version().is_ok()).await, Ok(true));
        drop(q);
        tokio::time::timeout(Duration::from_secs(5), task)
            .await
            .expect("the queue's task ends with its handles")
            .expect("task");
        let _ = std::fs::remove_dir_all(dir);
    }

    /// A job that holds the store (a lock, a slow disk) holds up the queue, not the caller;
    /// beyond its depth `try_call` says it is full at once and queues nothing.
    #[tokio::test]
    async fn a_stuck_store_fills_the_queue_without_blocking_the_caller() {
        let (store, dir) = temp_store("full");
        let (q, _task) = StoreQueue::spawn(store);
        let (release, hold) = std::sync::mpsc::channel::<()>();
        let stuck = q
            .try_call(move |_| {
                let _ = hold.recv_timeout(Duration::from_secs(10));
            })
            .expect("room");
        // Let the serving task take the stuck job off the queue.
        tokio::time::sleep(Duration::from_millis(50)).await;
        let mut queued = Vec::new();
        let full = loop {
            match q.try_call(|_| ()) {
                Ok(p) => queued.push(p),
                Err(e) => break e,
            }
            assert!(queued.len() <= DEPTH, "never full");
        };
        assert_eq!(full, QueueError::Full);
        assert_eq!(queued.len(), DEPTH);
        release.send(()).expect("release");
        stuck.await.expect("the stuck job ends");
        for p in queued {
            p.await
                .expect("every queued job runs once the store is free");
        }
        let _ = std::fs::remove_dir_all(dir);
    }
}
