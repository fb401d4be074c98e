//! Refinement jobs: durable records, a queue, and leases for the workers that run them.
//!
//! A job is `queued` → `running` (with progress) → `done`, `failed` or `cancelled`. Every change
//! is written to `<store>/jobs/<id>/job.json` (a synced temporary file renamed into place, the
//! rename synced) before it is visible, so a restarted server knows every job. A running job
//! holds a lease that its worker renews with each progress report; when a lease runs out (the
//! worker died or hung) or the server restarts, the job goes back to the queue for another
//! attempt, or fails once its attempts are spent: never stuck in `running`, never silently lost.
//!
//! A result is stored whole before the record says `done`: the refined frames and a
//! `result.json` naming the attempt go into a temporary directory renamed to `result/`. A server
//! that crashed between that rename and the record's update finds the result on opening and
//! marks the job done, so a finished job is never run to completion twice. Leftovers of
//! interrupted writes are removed on opening.

use std::collections::{BTreeMap, VecDeque};
use std::path::{Path, PathBuf};
use std::sync::{Mutex, MutexGuard};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use tokio::sync::{Notify, watch};

use crate::ServiceError;
use crate::faults;
use crate::store::{now, sync_dir, write_synced};

/// What a stored result says about itself (`result/result.json`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
struct ResultMarker {
    attempt: u32,
    worker: String,
    frames: usize,
    seconds: f64,
}

/// Where a job is in its life.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum JobState {
    /// Waiting for a worker.
    Queued,
    /// A worker has it.
    Running,
    /// Finished: the result is stored.
    Done,
    /// Gave up: `error` says why.
    Failed,
    /// Cancelled by a client.
    Cancelled,
}

impl JobState {
    /// True for states a job never leaves.
    pub fn is_terminal(self) -> bool {
        matches!(
            self,
            JobState::Done | JobState::Failed | JobState::Cancelled
        )
    }
}

/// Progress of a running job.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Progress {
    /// Steps done.
    pub step: u32,
    /// Steps in all.
    pub steps: u32,
    /// What the worker is doing.
    pub stage: String,
}

/// A job as stored and as the API shows it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct JobRecord {
    /// Job id.
    pub id: String,
    /// The clip it refines.
    pub clip_id: String,
    /// State.
    pub state: JobState,
    /// Attempt number, from 1.
    pub attempt: u32,
    /// Attempts allowed.
    pub max_attempts: u32,
    /// The worker running it.
    pub worker: Option<String>,
    /// Latest progress.
    pub progress: Option<Progress>,
    /// Why it failed.
    pub error: Option<String>,
    /// What happened to it, oldest first ("attempt 1: worker w1 stopped responding").
    pub history: Vec<String>,
    /// The request, as given.
    pub request: serde_json::Value,
    /// Refined frames stored.
    pub result_frames: usize,
    /// Seconds the successful attempt took on its worker.
    pub seconds: Option<f64>,
    /// Unix seconds.
    pub created_at: u64,
    /// Unix seconds.
    pub updated_at: u64,
    /// A cancellation was asked for while it ran.
    #[serde(default)]
    pub cancel_requested: bool,
}

struct Entry {
    record: JobRecord,
    updates: watch::Sender<JobRecord>,
    lease_until: Option<Instant>,
}

/// See the module documentation.
pub struct JobStore {
    dir: PathBuf,
    lease: Duration,
    max_attempts: u32,
    state: Mutex<State>,
    queued: Notify,
}

#[derive(Default)]
struct State {
    jobs: BTreeMap<String, Entry>,
    queue: VecDeque<String>,
    counter: u64,
}

impl JobStore {
    /// Opens the job store under `dir`. Jobs that were running when the server stopped go back
    /// to the queue (or fail, when out of attempts), unless their result was stored: those are
    /// done.
    pub fn open(dir: &Path, lease: Duration, max_attempts: u32) -> Result<Self, ServiceError> {
        std::fs::create_dir_all(dir)
            .map_err(|e| ServiceError::storage(format!("cannot create {}", dir.display()), &e))?;
        let store = Self {
            dir: dir.to_path_buf(),
            lease,
            max_attempts: max_attempts.max(1),
            state: Mutex::new(State::default()),
            queued: Notify::new(),
        };
        let mut records: Vec<JobRecord> = std::fs::read_dir(dir)
            .map_err(|e| ServiceError::storage(format!("cannot read {}", dir.display()), &e))?
            .flatten()
            .filter_map(|e| read_job_dir(&e.path()))
            .collect();
        records.sort_by(|a, b| (a.created_at, &a.id).cmp(&(b.created_at, &b.id)));
        {
            let mut state = store.lock();
            for mut record in records {
                if record.state == JobState::Running {
                    match store.stored_result(&record) {
                        Some(result) => complete(&mut record, &result, " (found after a restart)"),
                        None => {
                            store.retry_or_fail(&mut record, "the server restarted while it ran")
                        }
                    }
                    // On a full disk the change is kept in memory and written with the next one:
                    // refusing to start would serve nothing at all.
                    if let Err(e) = store.write(&record) {
                        tracing::error!(job = %record.id, "cannot store the job's new state: {e}");
                    }
                }
                if record.state == JobState::Queued {
                    state.queue.push_back(record.id.clone());
                }
                let (updates, _) = watch::channel(record.clone());
                state.jobs.insert(
                    record.id.clone(),
                    Entry {
                        record,
                        updates,
                        lease_until: None,
                    },
                );
            }
            tracing::info!(
                jobs = state.jobs.len(),
                queued = state.queue.len(),
                "job store opened"
            );
            metrics::gauge!("c4g_jobs_queued").set(state.queue.len() as f64);
        }
        Ok(store)
    }

    /// The result of `record`'s current attempt, when it is stored.
    fn stored_result(&self, record: &JobRecord) -> Option<ResultMarker> {
        let bytes = std::fs::read(self.result_dir(&record.id).join("result.json")).ok()?;
        let marker: ResultMarker = serde_json::from_slice(&bytes).ok()?;
        (marker.attempt == record.attempt).then_some(marker)
    }

    fn lock(&self) -> MutexGuard<'_, State> {
        self.state.lock().unwrap_or_else(|p| p.into_inner())
    }

    fn write(&self, record: &JobRecord) -> Result<(), ServiceError> {
        let dir = self.dir.join(&record.id);
        let json = serde_json::to_vec_pretty(record).map_err(|e| {
            ServiceError::Internal(format!("cannot serialise job {}: {e}", record.id))
        })?;
        let tmp = dir.join(".job.json.tmp");
        std::fs::create_dir_all(&dir)
            .and_then(|()| sync_dir(&self.dir))
            .and_then(|()| write_synced(&tmp, &json))
            .and_then(|()| std::fs::rename(&tmp, dir.join("job.json")))
            .and_then(|()| sync_dir(&dir))
            .map_err(|e| {
                let _ = std::fs::remove_file(&tmp);
                ServiceError::storage(format!("cannot store job {}", record.id), &e)
            })
    }

    /// Applies `change` to job `id`, stores and publishes the result.
    fn update(
        &self,
        id: &str,
        change: impl FnOnce(&mut JobRecord, &mut Option<Instant>) -> Result<(), ServiceError>,
    ) -> Result<JobRecord, ServiceError> {
        let mut state = self.lock();
        let entry = state.jobs.get_mut(id).ok_or_else(|| not_found(id))?;
        let mut record = entry.record.clone();
        let mut lease = entry.lease_until;
        change(&mut record, &mut lease)?;
        record.updated_at = now();
        self.write(&record)?;
        entry.record = record.clone();
        entry.lease_until = lease;
        entry.updates.send_replace(record.clone());
        if record.state == JobState::Queued && !state.queue.contains(&record.id) {
            state.queue.push_back(record.id.clone());
            self.queued.notify_one();
        }
        metrics::gauge!("c4g_jobs_queued").set(state.queue.len() as f64);
        Ok(record)
    }

    fn retry_or_fail(&self, record: &mut JobRecord, why: &str) {
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

    /// Creates a queued job for `clip_id`.
    pub fn create(
        &self,
        clip_id: &str,
        request: serde_json::Value,
    ) -> Result<JobRecord, ServiceError> {
        let id = {
            let mut state = self.lock();
            state.counter += 1;
            let nanos = SystemTime::now()
                .duration_since(UNIX_EPOCH)
                .map(|d| d.as_nanos())
                .unwrap_or(0);
            let digest = Sha256::digest(format!("{nanos}-{}-{clip_id}", state.counter));
            format!("job-{}", hex::encode(&digest[..10]))
        };
        let record = JobRecord {
            id: id.clone(),
            clip_id: clip_id.to_owned(),
            state: JobState::Queued,
            attempt: 1,
            max_attempts: self.max_attempts,
            worker: None,
            progress: None,
            error: None,
            history: Vec::new(),
            request,
            result_frames: 0,
            seconds: None,
            created_at: now(),
            updated_at: now(),
            cancel_requested: false,
        };
        if let Err(e) = self.write(&record) {
            let _ = std::fs::remove_dir_all(self.dir.join(&id));
            return Err(e);
        }
        let mut state = self.lock();
        let (updates, _) = watch::channel(record.clone());
        state.jobs.insert(
            id.clone(),
            Entry {
                record: record.clone(),
                updates,
                lease_until: None,
            },
        );
        state.queue.push_back(id);
        metrics::gauge!("c4g_jobs_queued").set(state.queue.len() as f64);
        self.queued.notify_one();
        Ok(record)
    }

    /// One job's record.
    pub fn get(&self, id: &str) -> Result<JobRecord, ServiceError> {
        self.lock()
            .jobs
            .get(id)
            .map(|e| e.record.clone())
            .ok_or_else(|| not_found(id))
    }

    /// Every job, oldest first.
    pub fn list(&self) -> Vec<JobRecord> {
        let mut all: Vec<_> = self
            .lock()
            .jobs
            .values()
            .map(|e| e.record.clone())
            .collect();
        all.sort_by(|a, b| (a.created_at, &a.id).cmp(&(b.created_at, &b.id)));
        all
    }

    /// Updates of one job, as they happen.
    pub fn subscribe(&self, id: &str) -> Result<watch::Receiver<JobRecord>, ServiceError> {
        self.lock()
            .jobs
            .get(id)
            .map(|e| e.updates.subscribe())
            .ok_or_else(|| not_found(id))
    }

    /// The next queued job for `worker`, waiting up to `wait`.
    pub async fn take(
        &self,
        worker: &str,
        wait: Duration,
    ) -> Result<Option<JobRecord>, ServiceError> {
        let deadline = tokio::time::Instant::now() + wait;
        loop {
            let notified = self.queued.notified();
            let next = {
                let mut state = self.lock();
                let mut found = None;
                while let Some(id) = state.queue.pop_front() {
                    if state
                        .jobs
                        .get(&id)
                        .is_some_and(|e| e.record.state == JobState::Queued)
                    {
                        found = Some(id);
                        break;
                    }
                }
                found
            };
            if let Some(id) = next {
                let lease = self.lease;
                let record = self.update(&id, |record, lease_until| {
                    record.state = JobState::Running;
                    record.worker = Some(worker.to_owned());
                    record.progress = None;
                    *lease_until = Some(Instant::now() + lease);
                    Ok(())
                })?;
                return Ok(Some(record));
            }
            if tokio::time::timeout_at(deadline, notified).await.is_err() {
                return Ok(None);
            }
        }
    }

    /// Puts a job `worker` took back in the queue without counting the attempt, for a passing
    /// reason that says nothing about the job: the server could not hand it over (its work
    /// queue was full), or the worker is stopping (`Release`). A job cancelled meanwhile is
    /// cancelled instead.
    pub fn release(&self, id: &str, worker: &str, why: &str) -> Result<JobRecord, ServiceError> {
        self.update(id, |record, lease_until| {
            Self::check_owner(record, worker)?;
            *lease_until = None;
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
            Ok(())
        })
    }

    fn check_owner(record: &JobRecord, worker: &str) -> Result<(), ServiceError> {
        if record.state != JobState::Running || record.worker.as_deref() != Some(worker) {
            return Err(ServiceError::invalid(format!(
                "job {} is not running on worker {worker} (it is {:?}); drop it",
                record.id, record.state
            )));
        }
        Ok(())
    }

    /// Records progress (renewing the lease); `true` when the job was cancelled.
    pub fn progress(
        &self,
        id: &str,
        worker: &str,
        progress: Progress,
    ) -> Result<bool, ServiceError> {
        let lease = self.lease;
        let record = self.update(id, |record, lease_until| {
            Self::check_owner(record, worker)?;
            record.progress = Some(progress);
            *lease_until = Some(Instant::now() + lease);
            Ok(())
        })?;
        Ok(record.cancel_requested)
    }

    /// Stores the refined frames and marks the job done.
    pub fn finish(
        &self,
        id: &str,
        worker: &str,
        frames: &[Vec<u8>],
        seconds: f64,
    ) -> Result<JobRecord, ServiceError> {
        let current = self.get(id)?;
        Self::check_owner(&current, worker)?;
        let attempt = current.attempt;
        let marker = ResultMarker {
            attempt,
            worker: worker.to_owned(),
            frames: frames.len(),
            seconds,
        };
        let dir = self.result_dir(id);
        let job_dir = self.dir.join(id);
        let tmp = job_dir.join(".result.tmp");
        let _ = std::fs::remove_dir_all(&tmp);
        let stored = std::fs::create_dir_all(&tmp)
            .and_then(|()| {
                for (i, png) in frames.iter().enumerate() {
                    write_synced(&tmp.join(format!("{i:04}.png")), png)?;
                }
                let json = serde_json::to_vec_pretty(&marker).map_err(std::io::Error::other)?;
                write_synced(&tmp.join("result.json"), &json)?;
                sync_dir(&tmp)?;
                let _ = std::fs::remove_dir_all(&dir);
                std::fs::rename(&tmp, &dir)?;
                sync_dir(&job_dir)
            })
            .map_err(|e| ServiceError::storage(format!("cannot store the result of {id}"), &e));
        if let Err(e) = stored {
            let _ = std::fs::remove_dir_all(&tmp);
            return Err(e);
        }
        faults::pause("job-result-stored");
        let record = self.update(id, |record, lease_until| {
            Self::check_owner(record, worker)?;
            if record.attempt != attempt {
                return Err(ServiceError::invalid(format!(
                    "job {id} moved on to attempt {} while attempt {attempt} was stored; drop it",
                    record.attempt
                )));
            }
            complete(record, &marker, "");
            *lease_until = None;
            Ok(())
        });
        // A result the record does not take is removed, so that no restart mistakes it for one.
        if record.is_err() {
            let _ = std::fs::remove_dir_all(&dir);
        }
        let record = record?;
        metrics::counter!("c4g_jobs_total", "outcome" => "done").increment(1);
        Ok(record)
    }

    /// Records a failure reported by the worker.
    pub fn fail(
        &self,
        id: &str,
        worker: &str,
        error: &str,
        retryable: bool,
        cancelled: bool,
    ) -> Result<JobRecord, ServiceError> {
        self.update(id, |record, lease_until| {
            Self::check_owner(record, worker)?;
            *lease_until = None;
            if cancelled || record.cancel_requested {
                record.state = JobState::Cancelled;
                record.worker = None;
                record
                    .history
                    .push(format!("attempt {}: cancelled", record.attempt));
                metrics::counter!("c4g_jobs_total", "outcome" => "cancelled").increment(1);
            } else if retryable {
                self.retry_or_fail(record, &format!("worker {worker} failed: {error}"));
            } else {
                record.state = JobState::Failed;
                record.worker = None;
                record.error = Some(error.to_owned());
                record
                    .history
                    .push(format!("attempt {}: {error}", record.attempt));
                metrics::counter!("c4g_jobs_total", "outcome" => "failed").increment(1);
            }
            Ok(())
        })
    }

    /// Cancels a job: at once when queued, at the worker's next progress report when running.
    pub fn cancel(&self, id: &str) -> Result<JobRecord, ServiceError> {
        let record = self.update(id, |record, _| {
            match record.state {
                JobState::Queued => {
                    record.state = JobState::Cancelled;
                    record.history.push("cancelled while queued".into());
                    metrics::counter!("c4g_jobs_total", "outcome" => "cancelled").increment(1);
                }
                JobState::Running => record.cancel_requested = true,
                _ => {}
            }
            Ok(())
        })?;
        self.lock().queue.retain(|q| q != id);
        Ok(record)
    }

    /// Retries or fails every running job whose lease ran out. Returns how many.
    pub fn reap(&self) -> usize {
        let expired: Vec<(String, Option<String>)> = {
            let state = self.lock();
            let now = Instant::now();
            state
                .jobs
                .values()
                .filter(|e| {
                    e.record.state == JobState::Running && e.lease_until.is_some_and(|l| l < now)
                })
                .map(|e| (e.record.id.clone(), e.record.worker.clone()))
                .collect()
        };
        for (id, worker) in &expired {
            let why = format!(
                "worker {} stopped responding",
                worker.as_deref().unwrap_or("?")
            );
            let result = self.update(id, |record, lease_until| {
                *lease_until = None;
                self.retry_or_fail(record, &why);
                Ok(())
            });
            match result {
                Ok(record) => tracing::warn!(job = %id, state = ?record.state, "{why}"),
                Err(e) => tracing::error!(job = %id, "cannot requeue: {e}"),
            }
        }
        expired.len()
    }

    /// The directory of a job's refined frames.
    pub fn result_dir(&self, id: &str) -> PathBuf {
        self.dir.join(id).join("result")
    }
}

fn not_found(id: &str) -> ServiceError {
    ServiceError::NotFound(format!("no job {id:?} (GET /v1/jobs lists them)"))
}

/// Marks `record` done with the stored `result`.
fn complete(record: &mut JobRecord, result: &ResultMarker, note: &str) {
    record.state = JobState::Done;
    record.result_frames = result.frames;
    record.seconds = Some(result.seconds);
    record.history.push(format!(
        "attempt {}: done on {}{note}",
        record.attempt, result.worker
    ));
}

/// The record in job directory `dir`, cleaning up what interrupted writes left there. A
/// directory without a record is a creation that never finished (never answered): removed.
fn read_job_dir(dir: &Path) -> Option<JobRecord> {
    let name = dir.file_name()?.to_string_lossy().into_owned();
    if name.starts_with('.') || !dir.is_dir() {
        let _ = std::fs::remove_dir_all(dir).or_else(|_| std::fs::remove_file(dir));
        return None;
    }
    let _ = std::fs::remove_file(dir.join(".job.json.tmp"));
    let _ = std::fs::remove_dir_all(dir.join(".result.tmp"));
    let path = dir.join("job.json");
    let bytes = match std::fs::read(&path) {
        Ok(bytes) => bytes,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            tracing::info!(path = %dir.display(), "removing a job whose creation was interrupted");
            let _ = std::fs::remove_dir_all(dir);
            return None;
        }
        Err(e) => {
            tracing::warn!(path = %path.display(), "unreadable job skipped: {e}");
            return None;
        }
    };
    match serde_json::from_slice(&bytes) {
        Ok(record) => Some(record),
        Err(err) => {
            tracing::warn!(path = %path.display(), "unreadable job skipped: {err}");
            None
        }
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    fn store(dir: &Path, lease_ms: u64) -> JobStore {
        JobStore::open(dir, Duration::from_millis(lease_ms), 2).unwrap()
    }

    #[tokio::test]
    async fn a_lost_worker_gets_its_job_retried_then_failed_never_stuck() {
        let dir = tempfile::tempdir().unwrap();
        let jobs = store(dir.path(), 20);
        let job = jobs.create("clip", serde_json::json!({})).unwrap();
        let taken = jobs.take("w1", Duration::ZERO).await.unwrap().unwrap();
        assert_eq!(
            (taken.id.as_str(), taken.state),
            (job.id.as_str(), JobState::Running)
        );
        std::thread::sleep(Duration::from_millis(40));
        assert_eq!(jobs.reap(), 1);
        assert_eq!(jobs.get(&job.id).unwrap().state, JobState::Queued);
        // The first worker comes back too late: its reports are refused.
        assert!(
            jobs.progress(
                &job.id,
                "w1",
                Progress {
                    step: 1,
                    steps: 4,
                    stage: "denoising".into()
                }
            )
            .is_err()
        );
        let again = jobs.take("w2", Duration::ZERO).await.unwrap().unwrap();
        assert_eq!(again.attempt, 2);
        std::thread::sleep(Duration::from_millis(40));
        jobs.reap();
        let failed = jobs.get(&job.id).unwrap();
        assert_eq!(failed.state, JobState::Failed);
        assert!(failed.error.unwrap().contains("w2 stopped responding"));
        assert_eq!(failed.history.len(), 2);
    }

    #[tokio::test]
    async fn a_job_released_for_a_passing_reason_keeps_its_attempts() {
        let dir = tempfile::tempdir().unwrap();
        let jobs = store(dir.path(), 60_000);
        let job = jobs.create("clip", serde_json::json!({})).unwrap();
        // Busier than the job has attempts: never failed for it.
        for _ in 0..5 {
            let taken = jobs.take("w1", Duration::ZERO).await.unwrap().unwrap();
            assert_eq!(taken.attempt, 1);
            let released = jobs
                .release(&job.id, "w1", "the server is overloaded")
                .unwrap();
            assert_eq!((released.state, released.attempt), (JobState::Queued, 1));
        }
        // Only its taker may release it.
        jobs.take("w1", Duration::ZERO).await.unwrap().unwrap();
        assert!(jobs.release(&job.id, "w2", "busy").is_err());
    }

    #[tokio::test]
    async fn records_survive_a_restart_and_running_jobs_are_requeued() {
        let dir = tempfile::tempdir().unwrap();
        let id = {
            let jobs = store(dir.path(), 60_000);
            let job = jobs
                .create("clip", serde_json::json!({"steps": 4}))
                .unwrap();
            jobs.take("w1", Duration::ZERO).await.unwrap();
            job.id
        };
        let jobs = store(dir.path(), 60_000);
        let record = jobs.get(&id).unwrap();
        assert_eq!((record.state, record.attempt), (JobState::Queued, 2));
        assert_eq!(record.request["steps"], 4);
        let taken = jobs
            .take("w2", Duration::from_millis(10))
            .await
            .unwrap()
            .unwrap();
        jobs.finish(&id, "w2", &[vec![1, 2, 3]], 1.5).unwrap();
        let done = jobs.get(&taken.id).unwrap();
        assert_eq!((done.state, done.result_frames), (JobState::Done, 1));
        assert_eq!(
            std::fs::read(jobs.result_dir(&id).join("0000.png")).unwrap(),
            vec![1, 2, 3]
        );
    }

    #[tokio::test]
    async fn a_result_stored_before_a_crash_makes_the_job_done_not_run_again() {
        let dir = tempfile::tempdir().unwrap();
        let (stored, plain) = {
            let jobs = store(dir.path(), 60_000);
            let stored = jobs.create("clip", serde_json::json!({})).unwrap();
            let plain = jobs.create("clip", serde_json::json!({})).unwrap();
            jobs.take("w1", Duration::ZERO).await.unwrap();
            jobs.take("w2", Duration::ZERO).await.unwrap();
            // What a crash between storing the result and the record leaves: the result in
            // place, the record saying running.
            let result = jobs.result_dir(&stored.id);
            std::fs::create_dir_all(&result).unwrap();
            std::fs::write(result.join("0000.png"), [1, 2]).unwrap();
            let marker = ResultMarker {
                attempt: 1,
                worker: "w1".into(),
                frames: 1,
                seconds: 2.0,
            };
            std::fs::write(
                result.join("result.json"),
                serde_json::to_vec(&marker).unwrap(),
            )
            .unwrap();
            // And interrupted writes.
            std::fs::write(dir.path().join(&plain.id).join(".job.json.tmp"), b"{").unwrap();
            std::fs::create_dir_all(dir.path().join("job-never-created")).unwrap();
            (stored.id, plain.id)
        };
        let jobs = store(dir.path(), 60_000);
        let done = jobs.get(&stored).unwrap();
        assert_eq!(
            (done.state, done.attempt, done.result_frames),
            (JobState::Done, 1, 1)
        );
        assert!(done.history[0].contains("done on w1"), "{:?}", done.history);
        let requeued = jobs.get(&plain).unwrap();
        assert_eq!((requeued.state, requeued.attempt), (JobState::Queued, 2));
        let taken = jobs.take("w3", Duration::ZERO).await.unwrap().unwrap();
        assert_eq!(taken.id, plain, "the done job is never handed out");
        assert!(!dir.path().join(&plain).join(".job.json.tmp").exists());
        assert!(!dir.path().join("job-never-created").exists());
        assert_eq!(jobs.list().len(), 2);
    }

    #[tokio::test]
    async fn cancelling_a_queued_job_is_immediate_and_a_running_one_is_told() {
        let dir = tempfile::tempdir().unwrap();
        let jobs = store(dir.path(), 60_000);
        let queued = jobs.create("clip", serde_json::json!({})).unwrap();
        let running = jobs.create("clip", serde_json::json!({})).unwrap();
        assert_eq!(jobs.cancel(&queued.id).unwrap().state, JobState::Cancelled);
        let taken = jobs.take("w", Duration::ZERO).await.unwrap().unwrap();
        assert_eq!(
            taken.id, running.id,
            "the cancelled job is never handed out"
        );
        jobs.cancel(&running.id).unwrap();
        let progress = Progress {
            step: 1,
            steps: 2,
            stage: "denoising".into(),
        };
        assert!(jobs.progress(&running.id, "w", progress).unwrap());
        let record = jobs
            .fail(&running.id, "w", "cancelled", false, true)
            .unwrap();
        assert_eq!(record.state, JobState::Cancelled);
        assert!(
            jobs.take("w", Duration::from_millis(5))
                .await
                .unwrap()
                .is_none()
        );
    }
}
