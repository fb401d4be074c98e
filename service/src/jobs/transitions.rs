//! What each job call does to a record: pure functions that both stores apply under their own
//! lock (the disk store's mutex, a row's `FOR UPDATE`), so the two cannot drift apart. Each
//! returns what the change does to the job's lease; the stores keep leases in their own clock
//! (the process's, the database's).

use super::{JobRecord, JobState, Progress};
use crate::ServiceError;

/// What a change does to the job's lease.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Lease {
    /// Left as it is.
    Keep,
    /// Runs for the store's lease from now.
    Renew,
    /// No lease: the job is not running.
    Clear,
}

/// A queued job handed to `worker`.
pub fn take(record: &mut JobRecord, worker: &str) -> Lease {
    record.state = JobState::Running;
    record.worker = Some(worker.to_owned());
    record.progress = None;
    Lease::Renew
}

/// Refuses a report from anyone but the job's current worker.
pub fn check_owner(record: &JobRecord, worker: &str) -> Result<(), ServiceError> {
    if record.state != JobState::Running || record.worker.as_deref() != Some(worker) {
        return Err(ServiceError::invalid(format!(
            "job {} is not running on worker {worker} (it is {}); drop it",
            record.id,
            record.state.name()
        )));
    }
    Ok(())
}

/// Refuses a result of an attempt the job has moved on from.
pub fn check_attempt(record: &JobRecord, attempt: u32) -> Result<(), ServiceError> {
    if record.attempt != attempt {
        return Err(ServiceError::invalid(format!(
            "job {} moved on to attempt {} while attempt {attempt} was stored; drop it",
            record.id, record.attempt
        )));
    }
    Ok(())
}

/// See [`JobQueue::release`](super::JobQueue::release).
pub fn release(record: &mut JobRecord, worker: &str, why: &str) -> Result<Lease, ServiceError> {
    check_owner(record, worker)?;
    record.worker = None;
    record.progress = None;
    record.history.push(format!(
        "attempt {}: released from {worker} ({why}); queued again, the attempt not counted",
        record.attempt
    ));
    record.state = if record.cancel_requested {
        JobState::Cancelled
    } else {
        JobState::Queued
    };
    Ok(Lease::Clear)
}

/// Progress from the job's worker.
pub fn progress(
    record: &mut JobRecord,
    worker: &str,
    progress: Progress,
) -> Result<Lease, ServiceError> {
    check_owner(record, worker)?;
    record.progress = Some(progress);
    Ok(Lease::Renew)
}

/// See [`JobQueue::fail`](super::JobQueue::fail).
pub fn fail(
    record: &mut JobRecord,
    worker: &str,
    error: &str,
    retryable: bool,
    cancelled: bool,
) -> Result<Lease, ServiceError> {
    check_owner(record, worker)?;
    if cancelled || record.cancel_requested {
        record.state = JobState::Cancelled;
        record.worker = None;
        record
            .history
            .push(format!("attempt {}: cancelled", record.attempt));
        metrics::counter!("c4g_jobs_total", "outcome" => "cancelled").increment(1);
    } else if retryable {
        retry_or_fail(record, &format!("worker {worker} failed: {error}"));
    } else {
        record.state = JobState::Failed;
        record.worker = None;
        record.error = Some(error.to_owned());
        record
            .history
            .push(format!("attempt {}: {error}", record.attempt));
        metrics::counter!("c4g_jobs_total", "outcome" => "failed").increment(1);
    }
    Ok(Lease::Clear)
}

/// A client's cancellation: at once when queued, asked of the worker when running.
pub fn cancel(record: &mut JobRecord) -> Lease {
    match record.state {
        JobState::Queued => {
            record.state = JobState::Cancelled;
            record.history.push("cancelled while queued".into());
            metrics::counter!("c4g_jobs_total", "outcome" => "cancelled").increment(1);
        }
        JobState::Running => record.cancel_requested = true,
        JobState::Done | JobState::Failed | JobState::Cancelled => {}
    }
    Lease::Keep
}

/// A running job whose lease ran out: its worker is taken for lost.
pub fn expire(record: &mut JobRecord) -> Lease {
    let why = format!(
        "worker {} stopped responding",
        record.worker.as_deref().unwrap_or("?")
    );
    retry_or_fail(record, &why);
    tracing::warn!(job = %record.id, state = record.state.name(), "{why}");
    Lease::Clear
}

/// The job back in the queue for another attempt, or failed once its attempts are spent
/// (cancelled instead, when a cancellation was asked for).
pub fn retry_or_fail(record: &mut JobRecord, why: &str) {
    record
        .history
        .push(format!("attempt {}: {why}", record.attempt));
    record.worker = None;
    record.progress = None;
    if record.cancel_requested {
        record.state = JobState::Cancelled;
    } else if record.attempt < record.max_attempts {
        record.attempt += 1;
        record.state = JobState::Queued;
    } else {
        record.state = JobState::Failed;
        record.error = Some(format!(
            "{why} (attempt {} of {})",
            record.attempt, record.max_attempts
        ));
        metrics::counter!("c4g_jobs_total", "outcome" => "failed").increment(1);
    }
}

/// The job done with a stored result of `frames` frames from `worker` (`note` is added to its
/// history: how the result was found).
pub fn complete(
    record: &mut JobRecord,
    worker: &str,
    frames: usize,
    seconds: f64,
    note: &str,
) -> Lease {
    record.state = JobState::Done;
    record.result_frames = frames;
    record.seconds = Some(seconds);
    record.history.push(format!(
        "attempt {}: done on {worker}{note}",
        record.attempt
    ));
    Lease::Clear
}
