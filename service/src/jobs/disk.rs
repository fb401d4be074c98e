//! The default job store: one replica's jobs in its store directory.
//!
//! Every change is written to `<store>/jobs/<id>/job.json` (a synced temporary file renamed into
//! place, the rename synced) before it is visible, so a restarted server knows every job. Jobs
//! that were running when the server stopped go back to the queue for another attempt (their
//! workers talked to this server, which forgot their leases), unless their result was stored.
//!
//! A result is stored whole before the record says `done`: the refined frames and a
//! `result.json` naming the attempt go into a temporary directory renamed to `result/`. A server
//! that crashed between that rename and the record's update finds the result on opening and
//! marks the job done, so a finished job is never run to completion twice. Leftovers of
//! interrupted writes are removed on opening.

use std::collections::{BTreeMap, VecDeque};
use std::path::{Path, PathBuf};
use std::sync::{Mutex, MutexGuard};
use std::time::{Duration, Instant};

use serde::{Deserialize, Serialize};
use tokio::sync::{Notify, watch};

use super::transitions::{self, Lease};
use super::{JobQueue, JobRecord, JobState, Progress, not_found};
use crate::ServiceError;
use crate::clips::durable::{sync_dir, write_synced};
use crate::clips::record::now;
use crate::faults;

/// What a stored result says about itself (`result/result.json`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
struct ResultMarker {
    attempt: u32,
    worker: String,
    frames: usize,
    seconds: f64,
}

struct Entry {
    /// Creation order (records say the second only; jobs made before a restart are ordered by
    /// that second, then id).
    seq: u64,
    record: JobRecord,
    updates: watch::Sender<JobRecord>,
    lease_until: Option<Instant>,
}

/// See the module documentation.
pub struct DiskJobs {
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
    created: u64,
}

impl DiskJobs {
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
                        Some(result) => {
                            transitions::complete(
                                &mut record,
                                &result.worker,
                                result.frames,
                                result.seconds,
                                " (found after a restart)",
                            );
                        }
                        None => transitions::retry_or_fail(
                            &mut record,
                            "the server restarted while it ran",
                        ),
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
                state.created += 1;
                let seq = state.created;
                state.jobs.insert(
                    record.id.clone(),
                    Entry {
                        seq,
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
        change: impl FnOnce(&mut JobRecord) -> Result<Lease, ServiceError>,
    ) -> Result<JobRecord, ServiceError> {
        let mut state = self.lock();
        let entry = state.jobs.get_mut(id).ok_or_else(|| not_found(id))?;
        let mut record = entry.record.clone();
        let lease = change(&mut record)?;
        record.updated_at = now();
        self.write(&record)?;
        entry.record = record.clone();
        entry.lease_until = match lease {
            Lease::Keep => entry.lease_until,
            Lease::Renew => Some(Instant::now() + self.lease),
            Lease::Clear => None,
        };
        entry.updates.send_replace(record.clone());
        if record.state == JobState::Queued && !state.queue.contains(&record.id) {
            state.queue.push_back(record.id.clone());
            self.queued.notify_one();
        }
        if record.state != JobState::Queued {
            state.queue.retain(|q| q != id);
        }
        metrics::gauge!("c4g_jobs_queued").set(state.queue.len() as f64);
        Ok(record)
    }

    /// The directory of a job's refined frames.
    fn result_dir(&self, id: &str) -> PathBuf {
        self.dir.join(id).join("result")
    }
}

#[async_trait::async_trait]
impl JobQueue for DiskJobs {
    fn kind(&self) -> &'static str {
        "disk"
    }

    async fn create(
        &self,
        clip_id: &str,
        request: serde_json::Value,
    ) -> Result<JobRecord, ServiceError> {
        let record = JobRecord::new(clip_id, request, self.max_attempts);
        let id = record.id.clone();
        if let Err(e) = self.write(&record) {
            let _ = std::fs::remove_dir_all(self.dir.join(&id));
            return Err(e);
        }
        let mut state = self.lock();
        let (updates, _) = watch::channel(record.clone());
        state.created += 1;
        let seq = state.created;
        state.jobs.insert(
            id.clone(),
            Entry {
                seq,
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

    async fn get(&self, id: &str) -> Result<JobRecord, ServiceError> {
        self.lock()
            .jobs
            .get(id)
            .map(|e| e.record.clone())
            .ok_or_else(|| not_found(id))
    }

    async fn list(&self) -> Result<Vec<JobRecord>, ServiceError> {
        let mut all: Vec<_> = self
            .lock()
            .jobs
            .values()
            .map(|e| (e.seq, e.record.clone()))
            .collect();
        all.sort_by_key(|(seq, _)| *seq);
        Ok(all.into_iter().map(|(_, record)| record).collect())
    }

    async fn queued(&self) -> Result<usize, ServiceError> {
        Ok(self.lock().queue.len())
    }

    async fn subscribe(&self, id: &str) -> Result<watch::Receiver<JobRecord>, ServiceError> {
        self.lock()
            .jobs
            .get(id)
            .map(|e| e.updates.subscribe())
            .ok_or_else(|| not_found(id))
    }

    async fn take(&self, worker: &str, wait: Duration) -> Result<Option<JobRecord>, ServiceError> {
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
                let record = self.update(&id, |record| Ok(transitions::take(record, worker)))?;
                return Ok(Some(record));
            }
            if tokio::time::timeout_at(deadline, notified).await.is_err() {
                return Ok(None);
            }
        }
    }

    async fn release(&self, id: &str, worker: &str, why: &str) -> Result<JobRecord, ServiceError> {
        self.update(id, |record| transitions::release(record, worker, why))
    }

    async fn progress(
        &self,
        id: &str,
        worker: &str,
        progress: Progress,
    ) -> Result<bool, ServiceError> {
        let record = self.update(id, |record| transitions::progress(record, worker, progress))?;
        Ok(record.cancel_requested)
    }

    async fn finish(
        &self,
        id: &str,
        worker: &str,
        frames: Vec<Vec<u8>>,
        seconds: f64,
    ) -> Result<JobRecord, ServiceError> {
        let current = self.get(id).await?;
        transitions::check_owner(&current, worker)?;
        let attempt = current.attempt;
        let marker = ResultMarker {
            attempt,
            worker: worker.to_owned(),
            frames: frames.len(),
            seconds,
        };
        let (dir, job_dir) = (self.result_dir(id), self.dir.join(id));
        // Frames are many synced writes: off the async threads.
        let stored = {
            let (dir, marker) = (dir.clone(), marker.clone());
            tokio::task::spawn_blocking(move || store_result(&job_dir, &dir, &frames, &marker))
                .await
                .map_err(|e| ServiceError::Internal(format!("storing a result panicked: {e}")))?
        };
        stored
            .map_err(|e| ServiceError::storage(format!("cannot store the result of {id}"), &e))?;
        faults::pause("job-result-stored");
        let record = self.update(id, |record| {
            transitions::check_owner(record, worker)?;
            transitions::check_attempt(record, attempt)?;
            Ok(transitions::complete(
                record,
                worker,
                marker.frames,
                marker.seconds,
                "",
            ))
        });
        // A result the record does not take is removed, so that no restart mistakes it for one.
        if record.is_err() {
            let _ = std::fs::remove_dir_all(&dir);
        }
        let record = record?;
        metrics::counter!("c4g_jobs_total", "outcome" => "done").increment(1);
        Ok(record)
    }

    async fn fail(
        &self,
        id: &str,
        worker: &str,
        error: &str,
        retryable: bool,
        cancelled: bool,
    ) -> Result<JobRecord, ServiceError> {
        self.update(id, |record| {
            transitions::fail(record, worker, error, retryable, cancelled)
        })
    }

    async fn cancel(&self, id: &str) -> Result<JobRecord, ServiceError> {
        self.update(id, |record| Ok(transitions::cancel(record)))
    }

    async fn reap(&self) -> Result<usize, ServiceError> {
        let expired: Vec<String> = {
            let state = self.lock();
            let now = Instant::now();
            state
                .jobs
                .values()
                .filter(|e| {
                    e.record.state == JobState::Running && e.lease_until.is_some_and(|l| l < now)
                })
                .map(|e| e.record.id.clone())
                .collect()
        };
        for id in &expired {
            let result = self.update(id, |record| Ok(transitions::expire(record)));
            if let Err(e) = result {
                tracing::error!(job = %id, "cannot requeue: {e}");
            }
        }
        Ok(expired.len())
    }

    async fn prune(&self, age: Duration) -> Result<usize, ServiceError> {
        let cutoff = now().saturating_sub(age.as_secs());
        let doomed: Vec<String> = self
            .lock()
            .jobs
            .values()
            .filter(|e| e.record.state.is_terminal() && e.record.updated_at <= cutoff)
            .map(|e| e.record.id.clone())
            .collect();
        for id in &doomed {
            // Out of the index first: a restart finds either the whole job or a directory it
            // removes as a leftover (renamed to a dot-name before it is deleted).
            self.lock().jobs.remove(id);
            let (dir, hidden) = (self.dir.join(id), self.dir.join(format!(".deleted-{id}")));
            std::fs::rename(&dir, &hidden)
                .and_then(|()| std::fs::remove_dir_all(&hidden))
                .map_err(|e| ServiceError::storage(format!("cannot delete job {id}"), &e))?;
        }
        Ok(doomed.len())
    }

    async fn result_frame(&self, id: &str, k: usize) -> Result<Vec<u8>, ServiceError> {
        let path = self.result_dir(id).join(format!("{k:04}.png"));
        match tokio::fs::read(&path).await {
            Ok(png) => Ok(png),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Err(ServiceError::NotFound(
                format!("job {id} has no refined frame {k}"),
            )),
            Err(e) => Err(ServiceError::Internal(format!(
                "cannot read a result frame: {e}"
            ))),
        }
    }
}

/// The frames and their marker written into `job_dir/.result.tmp`, then renamed to `dir`: a
/// result is there whole or not at all.
fn store_result(
    job_dir: &Path,
    dir: &Path,
    frames: &[Vec<u8>],
    marker: &ResultMarker,
) -> std::io::Result<()> {
    let tmp = job_dir.join(".result.tmp");
    let _ = std::fs::remove_dir_all(&tmp);
    let stored = std::fs::create_dir_all(&tmp).and_then(|()| {
        for (i, png) in frames.iter().enumerate() {
            write_synced(&tmp.join(format!("{i:04}.png")), png)?;
        }
        let json = serde_json::to_vec_pretty(marker).map_err(std::io::Error::other)?;
        write_synced(&tmp.join("result.json"), &json)?;
        sync_dir(&tmp)?;
        let _ = std::fs::remove_dir_all(dir);
        std::fs::rename(&tmp, dir)?;
        sync_dir(job_dir)
    });
    if stored.is_err() {
        let _ = std::fs::remove_dir_all(&tmp);
    }
    stored
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
    //! What is the disk store's own: restarts and interrupted writes. The behaviour both stores
    //! owe is tested against each in `tests/e2e/job_queues.rs`.
    #![allow(clippy::unwrap_used)]
    use super::*;

    fn store(dir: &Path, lease_ms: u64) -> DiskJobs {
        DiskJobs::open(dir, Duration::from_millis(lease_ms), 2).unwrap()
    }

    #[tokio::test]
    async fn records_survive_a_restart_and_running_jobs_are_requeued() {
        let dir = tempfile::tempdir().unwrap();
        let id = {
            let jobs = store(dir.path(), 60_000);
            let job = jobs
                .create("clip", serde_json::json!({"steps": 4}))
                .await
                .unwrap();
            jobs.take("w1", Duration::ZERO).await.unwrap();
            job.id
        };
        let jobs = store(dir.path(), 60_000);
        let record = jobs.get(&id).await.unwrap();
        assert_eq!((record.state, record.attempt), (JobState::Queued, 2));
        assert_eq!(record.request["steps"], 4);
        let taken = jobs
            .take("w2", Duration::from_millis(10))
            .await
            .unwrap()
            .unwrap();
        jobs.finish(&id, "w2", vec![vec![1, 2, 3]], 1.5)
            .await
            .unwrap();
        let done = jobs.get(&taken.id).await.unwrap();
        assert_eq!((done.state, done.result_frames), (JobState::Done, 1));
        assert_eq!(jobs.result_frame(&id, 0).await.unwrap(), vec![1, 2, 3]);
    }

    #[tokio::test]
    async fn a_result_stored_before_a_crash_makes_the_job_done_not_run_again() {
        let dir = tempfile::tempdir().unwrap();
        let (stored, plain) = {
            let jobs = store(dir.path(), 60_000);
            let stored = jobs.create("clip", serde_json::json!({})).await.unwrap();
            let plain = jobs.create("clip", serde_json::json!({})).await.unwrap();
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
        let done = jobs.get(&stored).await.unwrap();
        assert_eq!(
            (done.state, done.attempt, done.result_frames),
            (JobState::Done, 1, 1)
        );
        assert!(done.history[0].contains("done on w1"), "{:?}", done.history);
        let requeued = jobs.get(&plain).await.unwrap();
        assert_eq!((requeued.state, requeued.attempt), (JobState::Queued, 2));
        let taken = jobs.take("w3", Duration::ZERO).await.unwrap().unwrap();
        assert_eq!(taken.id, plain, "the done job is never handed out");
        assert!(!dir.path().join(&plain).join(".job.json.tmp").exists());
        assert!(!dir.path().join("job-never-created").exists());
        assert_eq!(jobs.list().await.unwrap().len(), 2);
    }
}
