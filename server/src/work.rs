//! Work slots: decodes and renders run on blocking threads, a bounded number at once, behind a
//! bounded queue.
//!
//! Decoding and rasterizing are CPU (or GPU) work: run on the async runtime's threads they would
//! stall health checks and streams, and run without a bound they would hold one decoder batch of
//! memory per request. So each piece of work waits for one of `C4G_MAX_CONCURRENT_WORK` slots;
//! at most `C4G_MAX_QUEUED_WORK` may wait, and more are refused at once (503 with `Retry-After`)
//! rather than queued without end. (Refinement *jobs* are something else: durable records that
//! workers pull, in `jobs`.)

use std::sync::Arc;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::Duration;

use tokio::sync::Semaphore;

use crate::ServiceError;

/// How long a client refused for a full queue should wait.
const RETRY_AFTER: Duration = Duration::from_secs(1);

/// The slots and the queue in front of them.
pub struct WorkSlots {
    slots: Arc<Semaphore>,
    capacity: usize,
    queued: AtomicUsize,
    max_queued: usize,
}

impl WorkSlots {
    /// `slots` pieces of work at once (0: one per core), `max_queued` waiting.
    pub fn new(slots: usize, max_queued: usize) -> Self {
        let slots = match slots {
            0 => std::thread::available_parallelism().map_or(2, |n| n.get()),
            n => n,
        };
        Self {
            slots: Arc::new(Semaphore::new(slots)),
            capacity: slots,
            queued: AtomicUsize::new(0),
            max_queued,
        }
    }

    /// Slots in all.
    pub fn capacity(&self) -> usize {
        self.capacity
    }

    /// Runs `work` on a blocking thread once a slot is free, or refuses it when the queue is
    /// full.
    pub async fn run<T: Send + 'static>(
        &self,
        work: impl FnOnce() -> Result<T, ServiceError> + Send + 'static,
    ) -> Result<T, ServiceError> {
        if self.queued.fetch_add(1, Ordering::SeqCst) >= self.max_queued {
            self.queued.fetch_sub(1, Ordering::SeqCst);
            metrics::counter!("c4g_rejected_total", "reason" => "queue_full").increment(1);
            return Err(ServiceError::Overloaded {
                retry_after: RETRY_AFTER,
            });
        }
        let permit = self.slots.clone().acquire_owned().await;
        self.queued.fetch_sub(1, Ordering::SeqCst);
        let permit =
            permit.map_err(|_| ServiceError::Internal("the work slots are closed".into()))?;
        tokio::task::spawn_blocking(move || {
            let _permit = permit;
            work()
        })
        .await
        .map_err(|e| ServiceError::Internal(format!("decode or render work panicked: {e}")))?
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn work_runs_and_its_error_comes_back() {
        let slots = WorkSlots::new(1, 4);
        assert_eq!(slots.run(|| Ok(2 + 2)).await.unwrap(), 4);
        let err = slots
            .run(|| Err::<(), _>(ServiceError::invalid("no")))
            .await
            .unwrap_err();
        assert_eq!(err.to_string(), "no");
    }

    #[tokio::test]
    async fn a_full_queue_refuses_at_once_with_a_retry_hint() {
        let slots = Arc::new(WorkSlots::new(1, 1));
        let (release, wait) = std::sync::mpsc::channel::<()>();
        let (started, running) = tokio::sync::oneshot::channel();
        // One piece of work holds the only slot...
        let busy = {
            let slots = slots.clone();
            tokio::spawn(async move {
                slots
                    .run(move || {
                        let _ = started.send(());
                        let _ = wait.recv();
                        Ok(())
                    })
                    .await
            })
        };
        running.await.unwrap();
        // ...one waits in the queue...
        let queued = {
            let slots = slots.clone();
            tokio::spawn(async move { slots.run(|| Ok(())).await })
        };
        while slots.queued.load(Ordering::SeqCst) == 0 {
            tokio::task::yield_now().await;
        }
        // ...and the next is refused.
        let err = slots.run(|| Ok(())).await.unwrap_err();
        assert!(matches!(err, ServiceError::Overloaded { .. }), "{err}");
        assert!(err.retry_after().is_some());
        release.send(()).unwrap();
        busy.await.unwrap().unwrap();
        queued.await.unwrap().unwrap();
    }
}
