//! Refinement jobs: durable records, a queue, and leases for the workers that run them.
//!
//! A job is `queued` → `running` (with progress) → `done`, `failed` or `cancelled`. A running
//! job holds a lease that its worker renews with each progress report; when a lease runs out
//! (the worker died or hung) the job goes back to the queue for another attempt, or fails once
//! its attempts are spent: never stuck in `running`, never silently lost. A result is stored
//! whole before the record says `done`, so a finished job is never run to completion twice.
//!
//! | module | holds |
//! |---|---|
//! | [`JobQueue`] (here) | the one interface the service calls, whichever store keeps the jobs |
//! | `transitions` | what each call does to a record: pure functions both stores apply under their own lock, so they cannot drift apart |
//! | [`disk`] | the default: one replica's jobs in its store directory |
//! | [`postgres`] | many replicas' jobs in one PostgreSQL database (`C4G_JOB_DATABASE`) |
//! | [`refine`] | what a refinement asks for, checked when submitted, and the video a worker gets |
//! | [`fit`] | what a fit asks for, the frames and start a fit worker gets, and its result kept as the clip's fitted scene |
//!
//! Both stores are held to the same behaviour by one set of tests (`tests/e2e/job_queues.rs`).

use std::path::Path;
use std::sync::Arc;
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use tokio::sync::watch;

use crate::ServiceError;
use crate::clips::record::now;
use crate::quoted;

pub mod disk;
pub mod fit;
pub mod postgres;
pub mod refine;
mod transitions;

pub use disk::DiskJobs;
pub use postgres::PostgresJobs;

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

    /// The state's name as stored and shown ("queued", ...).
    pub fn name(self) -> &'static str {
        match self {
            JobState::Queued => "queued",
            JobState::Running => "running",
            JobState::Done => "done",
            JobState::Failed => "failed",
            JobState::Cancelled => "cancelled",
        }
    }
}

/// Which queue a job is in: what it does.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum JobKind {
    /// A refinement of novel views (`c4g-refiner` workers).
    Refine,
    /// A fit of the clip's scene to its frames (`c4g-fitter` workers).
    Fit,
}

impl JobKind {
    /// The name the API shows.
    pub fn name(self) -> &'static str {
        match self {
            JobKind::Refine => "refine",
            JobKind::Fit => "fit",
        }
    }
}

/// Progress of a running job.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Progress {
    /// Steps done.
    pub step: u32,
    /// Steps in all.
    pub steps: u32,
    /// What the worker is doing.
    pub stage: String,
    /// A fit's loss at its latest step.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub loss: Option<f64>,
    /// A fit's mean PSNR on its held-out frames, when it last scored them.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub holdout_psnr: Option<f64>,
    /// A fit's Gaussians per keyframe.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub gaussians: Option<u64>,
    /// Seconds the worker has spent on this attempt.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub elapsed_s: Option<f64>,
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

impl JobRecord {
    /// A new queued job for `clip_id`, with a fresh id.
    fn new(clip_id: &str, request: serde_json::Value, max_attempts: u32) -> Self {
        // Ids must differ across replicas and restarts: the time, a random-enough salt from the
        // process and a counter, hashed.
        static COUNTER: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
        let count = COUNTER.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let nanos = SystemTime::now()
            .duration_since(UNIX_EPOCH)
            .map(|d| d.as_nanos())
            .unwrap_or(0);
        let digest = Sha256::digest(format!("{nanos}-{}-{count}-{clip_id}", std::process::id()));
        Self {
            id: format!("job-{}", hex::encode(&digest[..10])),
            clip_id: clip_id.to_owned(),
            state: JobState::Queued,
            attempt: 1,
            max_attempts,
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
        }
    }
}

/// Refinement jobs: records, the queue, worker leases and results. One replica's disk
/// ([`DiskJobs`]) or a database many replicas share ([`PostgresJobs`]); the service holds an
/// `Arc<dyn JobQueue>` and cannot tell them apart.
#[async_trait::async_trait]
pub trait JobQueue: Send + Sync {
    /// Which store: "disk" or "postgres" (logged at start).
    fn kind(&self) -> &'static str;
    /// A queued job for `clip_id`.
    async fn create(
        &self,
        clip_id: &str,
        request: serde_json::Value,
    ) -> Result<JobRecord, ServiceError>;
    /// One job.
    async fn get(&self, id: &str) -> Result<JobRecord, ServiceError>;
    /// Every job, oldest first.
    async fn list(&self) -> Result<Vec<JobRecord>, ServiceError>;
    /// Jobs waiting for a worker (for a shared store, cluster-wide: what a worker autoscaler
    /// reads as `c4g_jobs_queued`).
    async fn queued(&self) -> Result<usize, ServiceError>;
    /// Updates of one job as they happen (on any replica that shares the store).
    async fn subscribe(&self, id: &str) -> Result<watch::Receiver<JobRecord>, ServiceError>;
    /// The next queued job for `worker`, now running on its lease, waiting up to `wait`.
    async fn take(&self, worker: &str, wait: Duration) -> Result<Option<JobRecord>, ServiceError>;
    /// Back in the queue for a passing reason that says nothing about the job (the server could
    /// not hand it over, the worker is stopping): the attempt is not counted. Only its worker
    /// may release it; a job cancelled meanwhile is cancelled instead.
    async fn release(&self, id: &str, worker: &str, why: &str) -> Result<JobRecord, ServiceError>;
    /// Progress, renewing the lease; `true` when a cancellation was asked for.
    async fn progress(
        &self,
        id: &str,
        worker: &str,
        progress: Progress,
    ) -> Result<bool, ServiceError>;
    /// The refined frames (PNG) stored and the job done, as one step: refused, with nothing
    /// kept, unless `worker` still holds the job on the attempt it took.
    async fn finish(
        &self,
        id: &str,
        worker: &str,
        frames: Vec<Vec<u8>>,
        seconds: f64,
    ) -> Result<JobRecord, ServiceError>;
    /// A failure the worker reports: retried (a new attempt) when `retryable` and attempts are
    /// left, failed otherwise, cancelled when the worker stopped for a cancellation.
    async fn fail(
        &self,
        id: &str,
        worker: &str,
        error: &str,
        retryable: bool,
        cancelled: bool,
    ) -> Result<JobRecord, ServiceError>;
    /// Cancelled at once when queued, at the worker's next report when running.
    async fn cancel(&self, id: &str) -> Result<JobRecord, ServiceError>;
    /// Running jobs whose lease ran out, retried or failed; how many.
    async fn reap(&self) -> Result<usize, ServiceError>;
    /// Refined frame `k` (PNG) of a done job.
    async fn result_frame(&self, id: &str, k: usize) -> Result<Vec<u8>, ServiceError>;
    /// Deletes the jobs that ended (done, failed, cancelled) more than `age` ago, with their
    /// results; how many. Queued and running jobs are never touched.
    async fn prune(&self, age: Duration) -> Result<usize, ServiceError>;
}

/// Where a server keeps its jobs: `C4G_JOB_DATABASE` when set, else the store directory `dir`.
/// Jobs belong to a model (`model_key`): replicas of one model share them.
///
/// Connecting to a database blocks until it answers, so this runs off the async threads (the
/// server's loading task).
pub fn open(
    database: Option<&str>,
    dir: &Path,
    model_key: &str,
    lease: Duration,
    max_attempts: u32,
) -> Result<Arc<dyn JobQueue>, ServiceError> {
    let jobs: Arc<dyn JobQueue> = match database {
        None => Arc::new(DiskJobs::open(dir, lease, max_attempts)?),
        Some(url) => {
            let runtime = tokio::runtime::Handle::try_current().map_err(|_| {
                ServiceError::Internal("the job database is opened outside the runtime".into())
            })?;
            runtime.block_on(PostgresJobs::connect(url, model_key, lease, max_attempts))?
        }
    };
    tracing::info!(store = jobs.kind(), "refinement jobs");
    Ok(jobs)
}

/// Removes the refined videos in `dir` (a replica's cache of them) not touched for `age`: their
/// jobs are pruned, or will be, and any replica can make a video again while its job exists.
pub fn prune_videos(dir: &Path, age: Duration) -> usize {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return 0;
    };
    let old = |e: &std::fs::DirEntry| {
        e.metadata()
            .and_then(|m| m.modified())
            .ok()
            .and_then(|t| t.elapsed().ok())
            .is_some_and(|elapsed| elapsed >= age)
    };
    entries
        .flatten()
        .filter(|e| old(e) && std::fs::remove_file(e.path()).is_ok())
        .count()
}

fn not_found(id: &str) -> ServiceError {
    ServiceError::NotFound(format!(
        "no job {id_quoted} (GET /v1/jobs lists them)",
        id_quoted = quoted(id)
    ))
}
