//! Work slots: decodes and renders run on blocking threads, a bounded number at once, behind a
//! bounded queue.
//!
//! Decoding and rasterizing are CPU (or GPU) work: run on the async runtime's threads they would
//! stall health checks and streams, and run without a bound they would hold one decoder batch of
//! memory per request. So each piece of work waits for one of `C4G_MAX_CONCURRENT_WORK` slots;
//! at most `C4G_MAX_QUEUED_WORK` may wait, and more are refused at once (503 with `Retry-After`)
//! rather than queued without end. (Refinement *jobs* are something else: durable records that
//! workers pull, in `jobs`.)
//!
//! A request whose client goes away drops its [`WorkSlots::run`] future: waiting in the queue,
//! it leaves the queue at once; running, its work is told ([`stop_if_cancelled`]) and long work
//! (a trajectory's renders) stops at its next frame, freeing the slot. The gauges
//! `c4g_work_slots`, `c4g_work_slots_busy` and `c4g_work_queued` show where the slots are.

use std::cell::RefCell;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
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
    busy: Arc<AtomicUsize>,
    max_queued: usize,
}

thread_local! {
    /// Set while a work slot's thread runs a request's work: true once its request went away.
    static CANCELLED: RefCell<Option<Arc<AtomicBool>>> = const { RefCell::new(None) };
}

/// An error when the request the current work runs for went away (its client disconnected), so
/// that work made of many pieces stops between them; `Ok` otherwise, and always outside a work
/// slot. Nobody reads the error: it only ends the work.
pub fn stop_if_cancelled() -> Result<(), ServiceError> {
    let cancelled = CANCELLED.with(|c| {
        c.borrow()
            .as_ref()
            .is_some_and(|flag| flag.load(Ordering::SeqCst))
    });
    if cancelled {
        metrics::counter!("c4g_work_cancelled_total").increment(1);
        return Err(ServiceError::Internal(
            "the request went away: its work was cancelled".into(),
        ));
    }
    Ok(())
}

impl WorkSlots {
    /// `slots` pieces of work at once (0: one per core), `max_queued` waiting.
    pub fn new(slots: usize, max_queued: usize) -> Self {
        let slots = match slots {
            0 => std::thread::available_parallelism().map_or(2, |n| n.get()),
            n => n,
        };
        metrics::gauge!("c4g_work_slots").set(slots as f64);
        metrics::gauge!("c4g_work_slots_busy").set(0.0);
        metrics::gauge!("c4g_work_queued").set(0.0);
        Self {
            slots: Arc::new(Semaphore::new(slots)),
            capacity: slots,
            queued: AtomicUsize::new(0),
            busy: Arc::new(AtomicUsize::new(0)),
            max_queued,
        }
    }

    /// Slots in all.
    pub fn capacity(&self) -> usize {
        self.capacity
    }

    /// Runs `work` on a blocking thread once a slot is free, or refuses it when the queue is
    /// full. Dropping the future (the client went away) takes it out of the queue, or tells the
    /// running work through [`stop_if_cancelled`].
    pub async fn run<T: Send + 'static>(
        &self,
        work: impl FnOnce() -> Result<T, ServiceError> + Send + 'static,
    ) -> Result<T, ServiceError> {
        let permit = {
            let _waiting = Queued::enter(&self.queued, self.max_queued)?;
            self.slots.clone().acquire_owned().await
        };
        let permit =
            permit.map_err(|_| ServiceError::Internal("the work slots are closed".into()))?;
        let cancelled = Arc::new(AtomicBool::new(false));
        let _cancel_on_drop = CancelOnDrop(cancelled.clone());
        let busy = self.busy.clone();
        tokio::task::spawn_blocking(move || {
            let _permit = permit;
            let _running = Running::enter(busy, cancelled);
            work()
        })
        .await
        .map_err(|e| ServiceError::Internal(format!("decode or render work panicked: {e}")))?
    }
}

/// A place in the queue, given back however the wait ends (a slot, or the caller going away).
struct Queued<'a>(&'a AtomicUsize);

impl<'a> Queued<'a> {
    fn enter(queued: &'a AtomicUsize, max: usize) -> Result<Self, ServiceError> {
        if queued.fetch_add(1, Ordering::SeqCst) >= max {
            queued.fetch_sub(1, Ordering::SeqCst);
            metrics::counter!("c4g_rejected_total", "reason" => "queue_full").increment(1);
            return Err(ServiceError::Overloaded {
                retry_after: RETRY_AFTER,
            });
        }
        metrics::gauge!("c4g_work_queued").increment(1.0);
        Ok(Self(queued))
    }
}

impl Drop for Queued<'_> {
    fn drop(&mut self) {
        self.0.fetch_sub(1, Ordering::SeqCst);
        metrics::gauge!("c4g_work_queued").decrement(1.0);
    }
}

/// Tells the work its request went away when the request's future is dropped (after the work
/// finished it tells nobody).
struct CancelOnDrop(Arc<AtomicBool>);

impl Drop for CancelOnDrop {
    fn drop(&mut self) {
        self.0.store(true, Ordering::SeqCst);
    }
}

/// A slot's thread at work: counted busy, and its request's cancellation in reach of
/// [`stop_if_cancelled`], until the work ends (or panics).
struct Running(Arc<AtomicUsize>);

impl Running {
    fn enter(busy: Arc<AtomicUsize>, cancelled: Arc<AtomicBool>) -> Self {
        busy.fetch_add(1, Ordering::SeqCst);
        metrics::gauge!("c4g_work_slots_busy").increment(1.0);
        CANCELLED.with(|c| *c.borrow_mut() = Some(cancelled));
        Self(busy)
    }
}

impl Drop for Running {
    fn drop(&mut self) {
        CANCELLED.with(|c| *c.borrow_mut() = None);
        self.0.fetch_sub(1, Ordering::SeqCst);
        metrics::gauge!("c4g_work_slots_busy").decrement(1.0);
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

    #[tokio::test]
    async fn a_caller_that_goes_away_leaves_the_queue_and_cancels_its_running_work() {
        let slots = Arc::new(WorkSlots::new(1, 1));
        let (release, wait) = std::sync::mpsc::channel::<()>();
        let (started, running) = tokio::sync::oneshot::channel();
        let (stopped_tx, stopped) = std::sync::mpsc::channel();
        // Work of many pieces, checking between them, whose caller goes away.
        let long = {
            let slots = slots.clone();
            tokio::spawn(async move {
                slots
                    .run(move || {
                        let _ = started.send(());
                        let _ = wait.recv();
                        let outcome = stop_if_cancelled();
                        let _ = stopped_tx.send(outcome.is_err());
                        outcome
                    })
                    .await
            })
        };
        running.await.unwrap();
        // A caller waiting in the queue goes away: its place is given back.
        let waiting = {
            let slots = slots.clone();
            tokio::spawn(async move { slots.run(|| Ok(())).await })
        };
        while slots.queued.load(Ordering::SeqCst) == 0 {
            tokio::task::yield_now().await;
        }
        waiting.abort();
        let _ = waiting.await;
        assert_eq!(slots.queued.load(Ordering::SeqCst), 0);
        long.abort();
        let _ = long.await;
        release.send(()).unwrap();
        let stopped = tokio::task::spawn_blocking(move || stopped.recv().unwrap())
            .await
            .unwrap();
        assert!(
            stopped,
            "the running work was not told its caller went away"
        );
        while slots.busy.load(Ordering::SeqCst) > 0 {
            tokio::task::yield_now().await;
        }
        assert!(
            stop_if_cancelled().is_ok(),
            "outside a slot nothing is cancelled"
        );
        assert_eq!(slots.run(|| Ok(7)).await.unwrap(), 7);
    }
}
