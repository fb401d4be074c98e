//! Refinement jobs in PostgreSQL, for many replicas (`C4G_JOB_DATABASE=postgres://...`).
//!
//! - One row per job: the whole record as `jsonb` (the record type the disk store writes), its
//!   state, model and lease in columns for the queries. Every change is one transaction: the
//!   row locked (`FOR UPDATE`), the transition applied (`transitions`, as on disk), the row
//!   written, `pg_notify` sent (delivered on commit). `take` and `reap` lock with `FOR UPDATE SKIP
//!   LOCKED`, so replicas never wait on, or hand out, each other's rows.
//! - Leases are in the database's clock (`now()`), so replicas' clocks never disagree about one.
//!   A replica that restarts does not requeue running jobs (their workers may be talking to
//!   another replica): only an expired lease does, found by whichever replica reaps first.
//! - A result's frames go in `c4g_job_frames` in the same transaction that marks the job done:
//!   no crash window, and any replica serves them.
//! - Each replica keeps one `LISTEN c4g_jobs` connection: a notification (payload: the job id)
//!   refreshes that job's followers (server-sent events) and wakes waiting takers; while the
//!   listener is down (it reconnects) takers poll once a second.
//! - Jobs belong to the model they were made for (its key): replicas of another model, sharing
//!   the database during an upgrade, neither list nor take them.
//! - A database that cannot be reached is kind `unavailable` (503 / UNAVAILABLE, retry): the
//!   request failed, nothing was changed. That holds from the start: a database that is down
//!   when the server starts (containers start in any order) is logged, not fatal; the tables are
//!   made by the first call that reaches it.
//!
//! Connections are plain TCP or a Unix socket (`?host=/run/postgresql`): TLS to the database is
//! not built in; `docs/deploy.md` says how to keep that traffic private.

use std::collections::HashMap;
use std::sync::{Arc, Mutex, Weak};
use std::time::Duration;

use deadpool_postgres::{Manager, ManagerConfig, Pool, RecyclingMethod, Runtime, Timeouts};
use tokio::sync::{Notify, watch};
use tokio_postgres::{NoTls, Transaction};

use super::transitions::{self, Lease};
use super::{JobQueue, JobRecord, Progress, not_found};
use crate::ServiceError;

/// Created when missing, under an advisory lock: replicas starting together race otherwise.
const SCHEMA: &str = "
CREATE TABLE IF NOT EXISTS c4g_jobs (
    seq bigserial UNIQUE,
    id text PRIMARY KEY,
    model text NOT NULL,
    state text NOT NULL,
    record jsonb NOT NULL,
    lease_until timestamptz
);
CREATE INDEX IF NOT EXISTS c4g_jobs_queue ON c4g_jobs (model, seq) WHERE state = 'queued';
CREATE INDEX IF NOT EXISTS c4g_jobs_leases ON c4g_jobs (lease_until) WHERE state = 'running';
CREATE TABLE IF NOT EXISTS c4g_job_frames (
    job_id text NOT NULL REFERENCES c4g_jobs (id) ON DELETE CASCADE,
    frame integer NOT NULL,
    png bytea NOT NULL,
    PRIMARY KEY (job_id, frame)
);";

/// Any 64-bit number of our own: the advisory lock that serialises schema creation.
const SCHEMA_LOCK: i64 = 0x6334_675f_6a6f_6273;

/// The notification channel.
const CHANNEL: &str = "c4g_jobs";

/// How long a request waits for a connection, or a connection for the database, before it is
/// answered `unavailable`.
const CONNECT_TIMEOUT: Duration = Duration::from_secs(5);

/// See the module documentation.
pub struct PostgresJobs {
    pool: Pool,
    model: String,
    lease: Duration,
    max_attempts: u32,
    /// Followers of jobs, by id.
    watched: Mutex<HashMap<String, watch::Sender<JobRecord>>>,
    /// Woken by every notification.
    changed: Notify,
    /// Set once the tables are known to exist (made by the first call that reaches the
    /// database).
    schema: tokio::sync::OnceCell<()>,
}

/// A database failure: nothing was changed, and the client may retry.
fn db(e: impl std::fmt::Display) -> ServiceError {
    ServiceError::Unavailable(format!(
        "the job database failed or cannot be reached ({e}); nothing was changed (C4G_JOB_DATABASE)"
    ))
}

fn serialise(record: &JobRecord) -> Result<serde_json::Value, ServiceError> {
    serde_json::to_value(record)
        .map_err(|e| ServiceError::Internal(format!("cannot serialise job {}: {e}", record.id)))
}

fn decode(value: serde_json::Value) -> Result<JobRecord, ServiceError> {
    serde_json::from_value(value)
        .map_err(|e| ServiceError::Internal(format!("a stored job is unreadable: {e}")))
}

impl PostgresJobs {
    /// Connects to `url`, creating the tables when missing, and starts the listener. Jobs are
    /// those of the model `model`.
    pub async fn connect(
        url: &str,
        model: &str,
        lease: Duration,
        max_attempts: u32,
    ) -> Result<Arc<Self>, ServiceError> {
        let mut config: tokio_postgres::Config = url.parse().map_err(|e| {
            ServiceError::invalid(format!("C4G_JOB_DATABASE is not a PostgreSQL URL: {e}"))
        })?;
        if config.get_connect_timeout().is_none() {
            config.connect_timeout(CONNECT_TIMEOUT);
        }
        let manager = Manager::from_config(
            config.clone(),
            NoTls,
            ManagerConfig {
                recycling_method: RecyclingMethod::Fast,
            },
        );
        let pool = Pool::builder(manager)
            .max_size(16)
            .runtime(Runtime::Tokio1)
            .timeouts(Timeouts {
                wait: Some(CONNECT_TIMEOUT),
                create: Some(CONNECT_TIMEOUT),
                recycle: Some(CONNECT_TIMEOUT),
            })
            .build()
            .map_err(db)?;
        let jobs = Arc::new(Self {
            pool,
            model: model.to_owned(),
            lease,
            max_attempts: max_attempts.max(1),
            watched: Mutex::new(HashMap::new()),
            changed: Notify::new(),
            schema: tokio::sync::OnceCell::new(),
        });
        if let Err(e) = jobs.client().await {
            tracing::warn!("jobs answer unavailable until the job database can be reached: {e}");
        }
        tokio::spawn(listen(Arc::downgrade(&jobs), config));
        Ok(jobs)
    }

    /// A pooled connection, the tables made first if this is the first call to reach the
    /// database.
    async fn client(&self) -> Result<deadpool_postgres::Object, ServiceError> {
        let mut client = self.pool.get().await.map_err(db)?;
        let made = self.schema.get_or_try_init(|| async {
            let tx = client.transaction().await.map_err(db)?;
            tx.execute("SELECT pg_advisory_xact_lock($1)", &[&SCHEMA_LOCK])
                .await
                .map_err(db)?;
            tx.batch_execute(SCHEMA).await.map_err(db)?;
            tx.commit().await.map_err(db)?;
            tracing::info!("the job database is reachable");
            Ok::<(), ServiceError>(())
        });
        made.await?;
        Ok(client)
    }

    /// Locks job `id`, applies `change`, writes the row and notifies, in one transaction.
    async fn update(
        &self,
        id: &str,
        change: impl FnOnce(&mut JobRecord) -> Result<Lease, ServiceError> + Send,
    ) -> Result<JobRecord, ServiceError> {
        let mut client = self.client().await?;
        let tx = client.transaction().await.map_err(db)?;
        let mut record = self.locked(&tx, id).await?;
        let lease = match change(&mut record) {
            Ok(lease) => lease,
            Err(refused) => {
                // Rolled back before answering: a dropped transaction rolls back only when the
                // connection gets to it, and until then the row's lock makes other replicas'
                // takers (`SKIP LOCKED`) pass over a queued job.
                tx.rollback().await.map_err(db)?;
                return Err(refused);
            }
        };
        self.write(&tx, &mut record, lease).await?;
        tx.commit().await.map_err(db)?;
        Ok(record)
    }

    /// Writes `record` (stamped now) with its lease changed as `lease` says, and notifies.
    async fn write(
        &self,
        tx: &Transaction<'_>,
        record: &mut JobRecord,
        lease: Lease,
    ) -> Result<(), ServiceError> {
        record.updated_at = crate::clips::record::now();
        let json = serialise(record)?;
        let lease_ms = self.lease.as_secs_f64() * 1e3;
        let (renew, clear) = (lease == Lease::Renew, lease == Lease::Clear);
        tx.execute(
            "UPDATE c4g_jobs SET record = $2, state = $3,
               lease_until = CASE WHEN $4 THEN now() + $6 * interval '1 millisecond'
                                  WHEN $5 THEN NULL ELSE lease_until END
             WHERE id = $1",
            &[
                &record.id,
                &json,
                &record.state.name(),
                &renew,
                &clear,
                &lease_ms,
            ],
        )
        .await
        .map_err(db)?;
        tx.execute("SELECT pg_notify($1, $2)", &[&CHANNEL, &record.id])
            .await
            .map_err(db)?;
        Ok(())
    }

    /// Job `id`'s record, its row locked until `tx` ends.
    async fn locked(&self, tx: &Transaction<'_>, id: &str) -> Result<JobRecord, ServiceError> {
        let row = tx
            .query_opt(
                "SELECT record FROM c4g_jobs WHERE id = $1 AND model = $2 FOR UPDATE",
                &[&id, &self.model],
            )
            .await
            .map_err(db)?
            .ok_or_else(|| not_found(id))?;
        decode(row.get(0))
    }

    /// A queued job for `worker`, locked past other replicas' takers, now running.
    async fn take_one(&self, worker: &str) -> Result<Option<JobRecord>, ServiceError> {
        let mut client = self.client().await?;
        let tx = client.transaction().await.map_err(db)?;
        let Some(row) = tx
            .query_opt(
                "SELECT record FROM c4g_jobs WHERE state = 'queued' AND model = $1
                 ORDER BY seq LIMIT 1 FOR UPDATE SKIP LOCKED",
                &[&self.model],
            )
            .await
            .map_err(db)?
        else {
            return Ok(None);
        };
        let mut record = decode(row.get(0))?;
        let lease = transitions::take(&mut record, worker);
        self.write(&tx, &mut record, lease).await?;
        tx.commit().await.map_err(db)?;
        Ok(Some(record))
    }

    /// A notification for job `id`: takers wake, and its followers get the new record.
    async fn notified(&self, id: &str) {
        self.changed.notify_waiters();
        let followed = self
            .watched
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .get(id)
            .is_some_and(|s| s.receiver_count() > 0);
        if followed && let Ok(record) = self.get(id).await {
            self.publish(id, record);
        }
    }

    /// Every followed job read anew, and takers woken: after the listener was down.
    async fn catch_up(&self) {
        self.changed.notify_waiters();
        let followed: Vec<String> = {
            let mut watched = self.watched.lock().unwrap_or_else(|p| p.into_inner());
            watched.retain(|_, s| s.receiver_count() > 0);
            watched.keys().cloned().collect()
        };
        for id in followed {
            if let Ok(record) = self.get(&id).await {
                self.publish(&id, record);
            }
        }
    }

    /// `record` to job `id`'s followers, when it is news.
    fn publish(&self, id: &str, record: JobRecord) {
        if let Some(sender) = self
            .watched
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .get(id)
        {
            sender.send_if_modified(|current| {
                let news = *current != record;
                if news {
                    *current = record;
                }
                news
            });
        }
    }
}

#[async_trait::async_trait]
impl JobQueue for PostgresJobs {
    fn kind(&self) -> &'static str {
        "postgres"
    }

    async fn create(
        &self,
        clip_id: &str,
        request: serde_json::Value,
    ) -> Result<JobRecord, ServiceError> {
        let record = JobRecord::new(clip_id, request, self.max_attempts);
        let json = serialise(&record)?;
        let mut client = self.client().await?;
        let tx = client.transaction().await.map_err(db)?;
        tx.execute(
            "INSERT INTO c4g_jobs (id, model, state, record) VALUES ($1, $2, $3, $4)",
            &[&record.id, &self.model, &record.state.name(), &json],
        )
        .await
        .map_err(db)?;
        tx.execute("SELECT pg_notify($1, $2)", &[&CHANNEL, &record.id])
            .await
            .map_err(db)?;
        tx.commit().await.map_err(db)?;
        Ok(record)
    }

    async fn get(&self, id: &str) -> Result<JobRecord, ServiceError> {
        let client = self.client().await?;
        let row = client
            .query_opt(
                "SELECT record FROM c4g_jobs WHERE id = $1 AND model = $2",
                &[&id, &self.model],
            )
            .await
            .map_err(db)?
            .ok_or_else(|| not_found(id))?;
        decode(row.get(0))
    }

    async fn list(&self) -> Result<Vec<JobRecord>, ServiceError> {
        let client = self.client().await?;
        let rows = client
            .query(
                "SELECT record FROM c4g_jobs WHERE model = $1 ORDER BY seq",
                &[&self.model],
            )
            .await
            .map_err(db)?;
        rows.into_iter().map(|row| decode(row.get(0))).collect()
    }

    async fn queued(&self) -> Result<usize, ServiceError> {
        let client = self.client().await?;
        let row = client
            .query_one(
                "SELECT count(*) FROM c4g_jobs WHERE state = 'queued' AND model = $1",
                &[&self.model],
            )
            .await
            .map_err(db)?;
        let count: i64 = row.get(0);
        Ok(usize::try_from(count).unwrap_or(0))
    }

    async fn subscribe(&self, id: &str) -> Result<watch::Receiver<JobRecord>, ServiceError> {
        let record = self.get(id).await?;
        let receiver = {
            let mut watched = self.watched.lock().unwrap_or_else(|p| p.into_inner());
            watched.retain(|_, s| s.receiver_count() > 0);
            watched
                .entry(id.to_owned())
                .or_insert_with(|| watch::channel(record).0)
                .subscribe()
        };
        // A change between the read above and the follow would have gone unseen: read again.
        let now = self.get(id).await?;
        self.publish(id, now);
        Ok(receiver)
    }

    async fn take(&self, worker: &str, wait: Duration) -> Result<Option<JobRecord>, ServiceError> {
        let deadline = tokio::time::Instant::now() + wait;
        loop {
            let changed = self.changed.notified();
            if let Some(record) = self.take_one(worker).await? {
                return Ok(Some(record));
            }
            let now = tokio::time::Instant::now();
            if now >= deadline {
                return Ok(None);
            }
            let _ =
                tokio::time::timeout((deadline - now).min(Duration::from_secs(1)), changed).await;
        }
    }

    async fn release(&self, id: &str, worker: &str, why: &str) -> Result<JobRecord, ServiceError> {
        self.update(id, |record| transitions::release(record, worker, why))
            .await
    }

    async fn progress(
        &self,
        id: &str,
        worker: &str,
        progress: Progress,
    ) -> Result<bool, ServiceError> {
        let record = self
            .update(id, |record| transitions::progress(record, worker, progress))
            .await?;
        Ok(record.cancel_requested)
    }

    async fn finish(
        &self,
        id: &str,
        worker: &str,
        frames: Vec<Vec<u8>>,
        seconds: f64,
    ) -> Result<JobRecord, ServiceError> {
        let mut client = self.client().await?;
        let tx = client.transaction().await.map_err(db)?;
        let mut record = self.locked(&tx, id).await?;
        transitions::check_owner(&record, worker)?;
        tx.execute("DELETE FROM c4g_job_frames WHERE job_id = $1", &[&id])
            .await
            .map_err(db)?;
        for (k, png) in frames.iter().enumerate() {
            let k = i32::try_from(k)
                .map_err(|_| ServiceError::invalid("a result has too many frames"))?;
            tx.execute(
                "INSERT INTO c4g_job_frames (job_id, frame, png) VALUES ($1, $2, $3)",
                &[&id, &k, png],
            )
            .await
            .map_err(db)?;
        }
        let lease = transitions::complete(&mut record, worker, frames.len(), seconds, "");
        self.write(&tx, &mut record, lease).await?;
        tx.commit().await.map_err(db)?;
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
        .await
    }

    async fn cancel(&self, id: &str) -> Result<JobRecord, ServiceError> {
        self.update(id, |record| Ok(transitions::cancel(record)))
            .await
    }

    async fn reap(&self) -> Result<usize, ServiceError> {
        let mut client = self.client().await?;
        let tx = client.transaction().await.map_err(db)?;
        let rows = tx
            .query(
                "SELECT record FROM c4g_jobs
                 WHERE state = 'running' AND lease_until < now() AND model = $1
                 FOR UPDATE SKIP LOCKED",
                &[&self.model],
            )
            .await
            .map_err(db)?;
        for row in &rows {
            let mut record = decode(row.get(0))?;
            let lease = transitions::expire(&mut record);
            self.write(&tx, &mut record, lease).await?;
        }
        tx.commit().await.map_err(db)?;
        Ok(rows.len())
    }

    async fn prune(&self, age: Duration) -> Result<usize, ServiceError> {
        let cutoff = i64::try_from(crate::clips::record::now().saturating_sub(age.as_secs()))
            .unwrap_or(i64::MAX);
        let client = self.client().await?;
        // The records' own clock (`updated_at`, Unix seconds), as on disk; frames go with their
        // job (ON DELETE CASCADE).
        let deleted = client
            .execute(
                "DELETE FROM c4g_jobs WHERE model = $1
                   AND state IN ('done', 'failed', 'cancelled')
                   AND (record->>'updated_at')::bigint <= $2",
                &[&self.model, &cutoff],
            )
            .await
            .map_err(db)?;
        Ok(usize::try_from(deleted).unwrap_or(usize::MAX))
    }

    async fn result_frame(&self, id: &str, k: usize) -> Result<Vec<u8>, ServiceError> {
        let k = i32::try_from(k).map_err(|_| not_found(id))?;
        let client = self.client().await?;
        let row = client
            .query_opt(
                "SELECT png FROM c4g_job_frames WHERE job_id = $1 AND frame = $2",
                &[&id, &k],
            )
            .await
            .map_err(db)?
            .ok_or_else(|| ServiceError::NotFound(format!("job {id} has no refined frame {k}")))?;
        Ok(row.get(0))
    }
}

/// `LISTEN c4g_jobs` on a connection of its own, reconnecting after a pause when it drops, until
/// the store is dropped.
async fn listen(jobs: Weak<PostgresJobs>, config: tokio_postgres::Config) {
    use futures_util::StreamExt;
    loop {
        match config.connect(NoTls).await {
            Ok((client, mut connection)) => {
                let (tx, mut rx) = tokio::sync::mpsc::unbounded_channel();
                // The connection is driven here; notifications come out of it as messages.
                let driver = tokio::spawn(async move {
                    let mut messages =
                        futures_util::stream::poll_fn(move |cx| connection.poll_message(cx));
                    while let Some(Ok(message)) = messages.next().await {
                        if let tokio_postgres::AsyncMessage::Notification(n) = message {
                            let _ = tx.send(n.payload().to_owned());
                        }
                    }
                });
                match client.batch_execute("LISTEN c4g_jobs").await {
                    Ok(()) => {
                        // What changed while nobody listened: takers look again, followers
                        // read their jobs anew.
                        if let Some(jobs) = jobs.upgrade() {
                            jobs.catch_up().await;
                        }
                        while let Some(id) = rx.recv().await {
                            let Some(jobs) = jobs.upgrade() else { return };
                            jobs.notified(&id).await;
                        }
                        tracing::warn!("the job database's listener was cut; reconnecting");
                    }
                    Err(e) => tracing::warn!("the job database's listener cannot listen: {e}"),
                }
                driver.abort();
            }
            Err(e) => tracing::warn!("the job database's listener cannot connect: {e}"),
        }
        if jobs.strong_count() == 0 {
            return;
        }
        tokio::time::sleep(Duration::from_secs(1)).await;
    }
}
