//! The behaviour every job store owes (`c4g_service::jobs::JobQueue`), one function per rule, run
//! against the disk store and against PostgreSQL (a throwaway server from Debian's package,
//! `c4g_e2e::postgres`). Each rule gets two handles on one store: for the disk store the same
//! one twice (a replica's jobs are its own), for PostgreSQL two connections, as two replicas
//! sharing the database have; so "another replica" is part of every PostgreSQL case.
//!
//! Then what is PostgreSQL's own: jobs belong to their model, and a database outage is a clear
//! `unavailable` that passes when the database is back. (What is the disk store's own, restarts
//! and interrupted writes, is tested beside it in `service/src/jobs/disk.rs`.)

#![allow(clippy::unwrap_used, clippy::expect_used, missing_docs)]

use std::sync::Arc;
use std::time::Duration;

use c4g_e2e::postgres::TempPostgres;
use c4g_service::ServiceErrorKind;
use c4g_service::jobs::{DiskJobs, JobQueue, JobRecord, JobState, PostgresJobs, Progress};

/// The lease the rules run with: short, so lost workers are found quickly.
const LEASE: Duration = Duration::from_millis(300);

fn progress() -> Progress {
    Progress {
        step: 1,
        steps: 4,
        stage: "denoising".into(),
        ..Default::default()
    }
}

/// Two handles on one store.
type Pair = (Arc<dyn JobQueue>, Arc<dyn JobQueue>);

fn disk(dir: &tempfile::TempDir) -> Pair {
    let jobs: Arc<dyn JobQueue> = Arc::new(DiskJobs::open(dir.path(), LEASE, 2).unwrap());
    (jobs.clone(), jobs)
}

async fn postgres(db: &TempPostgres, model: &str) -> Pair {
    let a: Arc<dyn JobQueue> = PostgresJobs::connect(&db.url(), model, LEASE, 2)
        .await
        .unwrap();
    let b: Arc<dyn JobQueue> = PostgresJobs::connect(&db.url(), model, LEASE, 2)
        .await
        .unwrap();
    (a, b)
}

/// Runs `rule` on the disk store and on PostgreSQL (skipped outside CI when PostgreSQL is not
/// installed).
macro_rules! both_stores {
    ($($rule:ident),* $(,)?) => {
        mod disk_store {
            $(
                #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
                async fn $rule() {
                    let dir = tempfile::tempdir().unwrap();
                    let (a, b) = super::disk(&dir);
                    super::$rule(&*a, &*b).await;
                }
            )*
        }
        mod postgres_store {
            $(
                #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
                async fn $rule() {
                    let Some(db) = c4g_e2e::postgres::TempPostgres::start() else {
                        return;
                    };
                    let (a, b) = super::postgres(&db, "model").await;
                    super::$rule(&*a, &*b).await;
                }
            )*
        }
    };
}

both_stores!(
    a_lost_worker_gets_its_job_retried_then_failed_never_stuck,
    a_job_released_for_a_passing_reason_keeps_its_attempts,
    takers_at_once_get_distinct_jobs_and_a_job_finishes_once,
    a_waiting_taker_gets_a_job_created_meanwhile,
    cancelling_a_queued_job_is_immediate_and_a_running_one_is_told,
    a_follower_sees_every_change_wherever_it_is_made,
    a_retryable_failure_is_retried_and_a_final_one_is_not,
    the_queue_counts_what_waits_and_lists_oldest_first,
    jobs_that_ended_are_pruned_with_their_results_and_the_others_kept,
);

/// A lost worker's job is retried, then failed once its attempts are spent; the late worker's
/// reports are refused; a job whose lease ran out is reaped once, by one of the replicas.
async fn a_lost_worker_gets_its_job_retried_then_failed_never_stuck(
    a: &dyn JobQueue,
    b: &dyn JobQueue,
) {
    let job = a.create("clip", serde_json::json!({})).await.unwrap();
    let taken = b.take("w1", Duration::ZERO).await.unwrap().unwrap();
    assert_eq!(
        (taken.id.as_str(), taken.state),
        (job.id.as_str(), JobState::Running)
    );
    // Renewed by progress, the lease holds past its length.
    for _ in 0..3 {
        tokio::time::sleep(LEASE / 2).await;
        assert!(!a.progress(&job.id, "w1", progress()).await.unwrap());
        assert_eq!(a.reap().await.unwrap() + b.reap().await.unwrap(), 0);
    }
    tokio::time::sleep(LEASE * 2).await;
    let (ra, rb) = tokio::join!(a.reap(), b.reap());
    assert_eq!(ra.unwrap() + rb.unwrap(), 1, "reaped once in all");
    assert_eq!(a.get(&job.id).await.unwrap().state, JobState::Queued);
    let late = b.progress(&job.id, "w1", progress()).await.unwrap_err();
    assert_eq!(late.kind(), ServiceErrorKind::InvalidInput, "{late}");
    assert!(late.to_string().contains("drop it"), "{late}");
    let again = a.take("w2", Duration::ZERO).await.unwrap().unwrap();
    assert_eq!(again.attempt, 2);
    tokio::time::sleep(LEASE * 2).await;
    b.reap().await.unwrap();
    let failed = a.get(&job.id).await.unwrap();
    assert_eq!(failed.state, JobState::Failed);
    assert!(failed.error.unwrap().contains("w2 stopped responding"));
    assert_eq!(failed.history.len(), 2, "{:?}", failed.history);
}

/// Released for a passing reason, a job keeps its attempts however often; only its taker may
/// release it.
async fn a_job_released_for_a_passing_reason_keeps_its_attempts(
    a: &dyn JobQueue,
    b: &dyn JobQueue,
) {
    let job = a.create("clip", serde_json::json!({})).await.unwrap();
    for _ in 0..5 {
        let taken = b.take("w1", Duration::ZERO).await.unwrap().unwrap();
        assert_eq!(taken.attempt, 1);
        let released = a.release(&job.id, "w1", "busy").await.unwrap();
        assert_eq!((released.state, released.attempt), (JobState::Queued, 1));
    }
    b.take("w1", Duration::ZERO).await.unwrap().unwrap();
    assert!(a.release(&job.id, "w2", "busy").await.is_err());
    assert_eq!(b.get(&job.id).await.unwrap().worker.as_deref(), Some("w1"));
}

/// Takers on both replicas at once never get one job, and a job finishes once: a second
/// `finish` (a worker that retried its call) is refused and the first result stays, readable
/// from either replica.
async fn takers_at_once_get_distinct_jobs_and_a_job_finishes_once(
    a: &dyn JobQueue,
    b: &dyn JobQueue,
) {
    let mut want = Vec::new();
    for _ in 0..6 {
        want.push(a.create("clip", serde_json::json!({})).await.unwrap().id);
    }
    let takers = (0..6).map(|k| {
        let store = if k % 2 == 0 { a } else { b };
        async move {
            store
                .take(&format!("w{k}"), Duration::from_millis(500))
                .await
                .unwrap()
                .unwrap()
        }
    });
    let taken = futures_util::future::join_all(takers).await;
    let mut ids: Vec<String> = taken.iter().map(|r| r.id.clone()).collect();
    ids.sort();
    want.sort();
    assert_eq!(ids, want, "a job went to two takers, or one was left");
    let first = &taken[0];
    let worker = first.worker.clone().unwrap();
    let done = b
        .finish(&first.id, &worker, vec![vec![1, 2, 3], vec![4]], 1.5)
        .await
        .unwrap();
    assert_eq!((done.state, done.result_frames), (JobState::Done, 2));
    assert!(
        a.finish(&first.id, &worker, vec![vec![9]], 1.0)
            .await
            .is_err()
    );
    assert_eq!(a.result_frame(&first.id, 0).await.unwrap(), vec![1, 2, 3]);
    assert_eq!(b.result_frame(&first.id, 1).await.unwrap(), vec![4]);
    assert_eq!(
        a.result_frame(&first.id, 2).await.unwrap_err().kind(),
        ServiceErrorKind::NotFound
    );
    // A worker whose job went to another attempt cannot store a result for it.
    let other = &taken[1];
    a.fail(
        &other.id,
        other.worker.as_deref().unwrap(),
        "oom",
        true,
        false,
    )
    .await
    .unwrap();
    assert!(
        b.finish(
            &other.id,
            other.worker.as_deref().unwrap(),
            vec![vec![1]],
            1.0
        )
        .await
        .is_err()
    );
}

/// A waiting taker is woken by a job created meanwhile, on the other replica.
async fn a_waiting_taker_gets_a_job_created_meanwhile(a: &dyn JobQueue, b: &dyn JobQueue) {
    let started = std::time::Instant::now();
    let (taken, created) = tokio::join!(a.take("w1", Duration::from_secs(10)), async {
        tokio::time::sleep(Duration::from_millis(200)).await;
        b.create("clip", serde_json::json!({})).await.unwrap()
    });
    assert_eq!(taken.unwrap().unwrap().id, created.id);
    assert!(
        started.elapsed() < Duration::from_secs(5),
        "the taker was not woken: it found the job only after {:?}",
        started.elapsed()
    );
    // With nothing queued, a wait ends empty.
    assert!(
        a.take("w1", Duration::from_millis(50))
            .await
            .unwrap()
            .is_none()
    );
}

/// Cancelling a queued job is immediate; a running one is told at its next report, and is
/// cancelled (not failed) when its worker stops for it.
async fn cancelling_a_queued_job_is_immediate_and_a_running_one_is_told(
    a: &dyn JobQueue,
    b: &dyn JobQueue,
) {
    let queued = a.create("clip", serde_json::json!({})).await.unwrap();
    let running = a.create("clip", serde_json::json!({})).await.unwrap();
    assert_eq!(
        b.cancel(&queued.id).await.unwrap().state,
        JobState::Cancelled
    );
    let taken = a.take("w", Duration::ZERO).await.unwrap().unwrap();
    assert_eq!(
        taken.id, running.id,
        "the cancelled job is never handed out"
    );
    b.cancel(&running.id).await.unwrap();
    assert!(a.progress(&running.id, "w", progress()).await.unwrap());
    let record = b
        .fail(&running.id, "w", "cancelled", false, true)
        .await
        .unwrap();
    assert_eq!(record.state, JobState::Cancelled);
    assert!(
        a.take("w", Duration::from_millis(5))
            .await
            .unwrap()
            .is_none()
    );
    // A job that ended stays as it ended.
    assert_eq!(
        a.cancel(&running.id).await.unwrap().state,
        JobState::Cancelled
    );
}

/// A follower (the server-sent events of `GET /v1/jobs/{id}/events`) on one replica sees what
/// the worker's calls on the other do: taken, progress, done.
async fn a_follower_sees_every_change_wherever_it_is_made(a: &dyn JobQueue, b: &dyn JobQueue) {
    let job = a.create("clip", serde_json::json!({})).await.unwrap();
    let mut updates = a.subscribe(&job.id).await.unwrap();
    assert_eq!(updates.borrow_and_update().state, JobState::Queued);
    b.take("w", Duration::ZERO).await.unwrap().unwrap();
    let seen = wait_for(&mut updates, |r| r.state != JobState::Queued).await;
    assert_eq!(seen.state, JobState::Running);
    b.progress(&job.id, "w", progress()).await.unwrap();
    let seen = wait_for(&mut updates, |r| r.progress.is_some()).await;
    assert_eq!(seen.progress, Some(progress()));
    b.finish(&job.id, "w", vec![vec![7]], 0.5).await.unwrap();
    let seen = wait_for(&mut updates, |r| r.state.is_terminal()).await;
    assert_eq!((seen.state, seen.result_frames), (JobState::Done, 1));
}

/// The first record a follower sees that `done` accepts (within 5 s).
async fn wait_for(
    updates: &mut tokio::sync::watch::Receiver<JobRecord>,
    done: impl Fn(&JobRecord) -> bool,
) -> JobRecord {
    tokio::time::timeout(Duration::from_secs(5), updates.wait_for(|r| done(r)))
        .await
        .expect("a change made on the other replica never reached the follower")
        .unwrap()
        .clone()
}

/// A retryable failure the worker reports takes the next attempt; a final one fails the job at
/// once, with the worker's words.
async fn a_retryable_failure_is_retried_and_a_final_one_is_not(a: &dyn JobQueue, b: &dyn JobQueue) {
    let job = a.create("clip", serde_json::json!({})).await.unwrap();
    b.take("w1", Duration::ZERO).await.unwrap().unwrap();
    let retried = a
        .fail(&job.id, "w1", "out of memory", true, false)
        .await
        .unwrap();
    assert_eq!((retried.state, retried.attempt), (JobState::Queued, 2));
    b.take("w2", Duration::ZERO).await.unwrap().unwrap();
    let failed = a
        .fail(&job.id, "w2", "the clip has no frames", false, false)
        .await
        .unwrap();
    assert_eq!(failed.state, JobState::Failed);
    assert_eq!(failed.error.as_deref(), Some("the clip has no frames"));
    assert!(b.take("w3", Duration::ZERO).await.unwrap().is_none());
}

/// `queued` counts jobs waiting (what `c4g_jobs_queued` shows); `list` has every job, oldest
/// first, on either replica.
async fn the_queue_counts_what_waits_and_lists_oldest_first(a: &dyn JobQueue, b: &dyn JobQueue) {
    let mut made = Vec::new();
    for k in 0..3 {
        made.push(
            a.create(&format!("clip{k}"), serde_json::json!({"k": k}))
                .await
                .unwrap()
                .id,
        );
    }
    assert_eq!(b.queued().await.unwrap(), 3);
    b.take("w", Duration::ZERO).await.unwrap().unwrap();
    assert_eq!(a.queued().await.unwrap(), 2);
    let listed: Vec<String> = b.list().await.unwrap().into_iter().map(|r| r.id).collect();
    assert_eq!(listed, made);
    assert_eq!(
        a.get("job-none").await.unwrap_err().kind(),
        ServiceErrorKind::NotFound
    );
}

/// Pruning (`C4G_JOB_RETENTION_H`) deletes the jobs that ended, done, failed or cancelled, with
/// their results, and never a queued or running one; a younger cutoff keeps them all.
async fn jobs_that_ended_are_pruned_with_their_results_and_the_others_kept(
    a: &dyn JobQueue,
    b: &dyn JobQueue,
) {
    let mut ids = Vec::new();
    for _ in 0..5 {
        ids.push(a.create("clip", serde_json::json!({})).await.unwrap().id);
    }
    let taken: Vec<_> = futures_util::future::join_all((0..4).map(|k| {
        let store = if k % 2 == 0 { a } else { b };
        async move {
            store
                .take(&format!("w{k}"), Duration::ZERO)
                .await
                .unwrap()
                .unwrap()
        }
    }))
    .await;
    let (done, failed, cancelled, running) = (&taken[0], &taken[1], &taken[2], &taken[3]);
    a.finish(
        &done.id,
        done.worker.as_deref().unwrap(),
        vec![vec![1]],
        1.0,
    )
    .await
    .unwrap();
    b.fail(
        &failed.id,
        failed.worker.as_deref().unwrap(),
        "bad",
        false,
        false,
    )
    .await
    .unwrap();
    a.cancel(&cancelled.id).await.unwrap();
    b.fail(
        &cancelled.id,
        cancelled.worker.as_deref().unwrap(),
        "cancelled",
        false,
        true,
    )
    .await
    .unwrap();
    // Ended just now: a day's retention keeps them.
    assert_eq!(b.prune(Duration::from_secs(86_400)).await.unwrap(), 0);
    assert_eq!(a.list().await.unwrap().len(), 5);
    assert_eq!(b.prune(Duration::ZERO).await.unwrap(), 3);
    let left: Vec<String> = a.list().await.unwrap().into_iter().map(|r| r.id).collect();
    let queued = ids
        .iter()
        .find(|id| !taken.iter().any(|t| &t.id == *id))
        .unwrap();
    let mut want = vec![running.id.clone(), queued.clone()];
    want.sort();
    let mut got = left.clone();
    got.sort();
    assert_eq!(got, want, "only the queued and the running job are left");
    for gone in [&done.id, &failed.id, &cancelled.id] {
        assert_eq!(
            b.get(gone).await.unwrap_err().kind(),
            ServiceErrorKind::NotFound
        );
    }
    assert_eq!(
        a.result_frame(&done.id, 0).await.unwrap_err().kind(),
        ServiceErrorKind::NotFound
    );
    // The running job still reports and finishes.
    assert!(
        !b.progress(&running.id, running.worker.as_deref().unwrap(), progress())
            .await
            .unwrap()
    );
}

/// Replicas of another model share the database (an upgrade in progress) but not its jobs.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn jobs_belong_to_their_model() {
    let Some(db) = TempPostgres::start() else {
        return;
    };
    let (old, _) = postgres(&db, "model-a").await;
    let (new, _) = postgres(&db, "model-b").await;
    let job = old.create("clip", serde_json::json!({})).await.unwrap();
    assert!(new.take("w", Duration::ZERO).await.unwrap().is_none());
    assert_eq!(new.list().await.unwrap().len(), 0);
    assert_eq!(new.queued().await.unwrap(), 0);
    assert_eq!(
        new.get(&job.id).await.unwrap_err().kind(),
        ServiceErrorKind::NotFound
    );
    assert_eq!(
        old.take("w", Duration::ZERO).await.unwrap().unwrap().id,
        job.id
    );
}

/// A database that is down when the store opens (containers start in any order) is no reason to
/// stop: the store opens, answers `unavailable` until the database comes, then makes its tables
/// and works.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_database_down_at_start_is_unavailable_until_it_comes() {
    let Some(db) = TempPostgres::start() else {
        return;
    };
    db.pause();
    let jobs = PostgresJobs::connect(&db.url(), "model", LEASE, 2)
        .await
        .expect("opens without the database");
    let down = jobs
        .create("clip", serde_json::json!({}))
        .await
        .unwrap_err();
    assert_eq!(down.kind(), ServiceErrorKind::Unavailable, "{down}");
    assert!(down.to_string().contains("C4G_JOB_DATABASE"), "{down}");
    db.resume();
    let deadline = std::time::Instant::now() + Duration::from_secs(20);
    let job = loop {
        match jobs.create("clip", serde_json::json!({})).await {
            Ok(job) => break job,
            Err(e) => {
                assert!(std::time::Instant::now() < deadline, "never came: {e}");
                tokio::time::sleep(Duration::from_millis(200)).await;
            }
        }
    };
    assert_eq!(
        jobs.take("w", Duration::ZERO).await.unwrap().unwrap().id,
        job.id
    );
}

/// A database that goes away answers `unavailable` (503 / UNAVAILABLE, retry) within the
/// connect timeout, never hangs, and the store works again once it is back; a bad URL is refused
/// at start with what is wrong.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_database_outage_is_unavailable_and_passes() {
    let Some(db) = TempPostgres::start() else {
        return;
    };
    let (jobs, _) = postgres(&db, "model").await;
    let job = jobs.create("clip", serde_json::json!({})).await.unwrap();
    db.pause();
    let started = std::time::Instant::now();
    let down = jobs.get(&job.id).await.unwrap_err();
    assert_eq!(down.kind(), ServiceErrorKind::Unavailable, "{down}");
    assert!(down.to_string().contains("C4G_JOB_DATABASE"), "{down}");
    assert!(started.elapsed() < Duration::from_secs(15));
    assert_eq!(
        jobs.take("w", Duration::ZERO).await.unwrap_err().kind(),
        ServiceErrorKind::Unavailable
    );
    db.resume();
    let deadline = std::time::Instant::now() + Duration::from_secs(20);
    let back = loop {
        match jobs.get(&job.id).await {
            Ok(record) => break record,
            Err(e) => {
                assert!(std::time::Instant::now() < deadline, "never recovered: {e}");
                tokio::time::sleep(Duration::from_millis(200)).await;
            }
        }
    };
    assert_eq!(back.state, JobState::Queued, "the job survived the outage");
    assert_eq!(
        jobs.take("w", Duration::ZERO).await.unwrap().unwrap().id,
        job.id
    );

    let bad = PostgresJobs::connect("mysql://nope", "model", LEASE, 2)
        .await
        .err()
        .unwrap();
    assert_eq!(bad.kind(), ServiceErrorKind::InvalidInput, "{bad}");
}
