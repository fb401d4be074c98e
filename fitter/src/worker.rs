//! The worker's loop: takes a fit job from `c4g-server`, fits on a blocking thread, reports
//! progress (step, loss, held-out PSNR, Gaussian count, elapsed) at most every
//! [`REPORT_EVERY`] and after the last step (each report renews the job's lease, and its answer
//! says whether the job was cancelled), then sends the fitted scene or the failure.
//!
//! A worker that dies mid-fit simply stops reporting: the lease runs out and the job is retried
//! on another worker (from the start: a fit is minutes, and a retry of the same seed makes the
//! same scene), or failed once its attempts are spent. A worker asked to stop (`shutdown`) stops
//! its fit at the next step and hands the job back (`Release`: queued again, the attempt not
//! counted).

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use c4g_fit::Control;
use c4g_proto::v1 as pb;
use c4g_proto::worker::{Client, WorkerConfig, connect, stopping};
use tokio::sync::watch;

use crate::work::{self, WorkError};

/// How long one `TakeFit` waits for a job before asking again.
const TAKE_WAIT: Duration = Duration::from_secs(20);
/// Pause after a failed call to the server.
const RECONNECT_PAUSE: Duration = Duration::from_secs(1);
/// Least time between progress reports (well under any lease).
pub const REPORT_EVERY: Duration = Duration::from_millis(500);
/// Bytes of the scene per `FinishFit` message.
const PIECE: usize = 1 << 20;

/// Runs fit jobs until `shutdown` turns true.
pub async fn run(config: WorkerConfig, mut shutdown: watch::Receiver<bool>) -> Result<(), String> {
    let mut client = connect(&config)?;
    tracing::info!(server = %config.server, worker = %config.name, "fit worker started");
    loop {
        if *shutdown.borrow() {
            break;
        }
        let take = client.take_fit(pb::TakeFitRequest {
            worker: config.name.clone(),
            wait_ms: TAKE_WAIT.as_millis() as u32,
        });
        let take = tokio::select! {
            take = take => take,
            () = stopping(&mut shutdown) => break,
        };
        match take {
            Ok(response) => {
                if let Some(job) = response.into_inner().job {
                    run_job(&mut client, &config.name, job, &shutdown).await;
                }
            }
            Err(status) if status.code() == tonic::Code::Unauthenticated => {
                return Err(format!(
                    "the server refused this worker: {}",
                    status.message()
                ));
            }
            Err(status) => {
                tracing::warn!("cannot reach the server: {}", status.message());
                tokio::select! {
                    () = tokio::time::sleep(RECONNECT_PAUSE) => {}
                    () = stopping(&mut shutdown) => break,
                }
            }
        }
    }
    tracing::info!(worker = %config.name, "fit worker stopped");
    Ok(())
}

/// How a fit ended.
enum Ended {
    Fitted(Vec<u8>, work::Outcome),
    Failed(WorkError),
    /// Stopped: cancelled by the server, or this worker is stopping.
    Stopped,
}

async fn run_job(
    client: &mut Client,
    worker: &str,
    job: pb::FitJob,
    shutdown: &watch::Receiver<bool>,
) {
    let id = job.job_id.clone();
    tracing::info!(job = %id, attempt = job.attempt, frames = job.frames.len(), "fit started");
    let stop = Arc::new(AtomicBool::new(false));
    let (tx, mut latest) = watch::channel(None::<c4g_fit::Progress>);
    let fitting = {
        let stop = stop.clone();
        tokio::task::spawn_blocking(move || {
            let prepared = match work::prepare(&job) {
                Ok(p) => p,
                Err(e) => return Ended::Failed(e),
            };
            let result = work::run(&prepared, |p| {
                tx.send_replace(Some(*p));
                if stop.load(Ordering::Relaxed) {
                    Control::Stop
                } else {
                    Control::Continue
                }
            });
            match result {
                _ if stop.load(Ordering::Relaxed) => Ended::Stopped,
                Ok((scene, outcome)) => Ended::Fitted(scene, outcome),
                Err(e) => Ended::Failed(e),
            }
        })
    };
    let started = Instant::now();
    let mut cancelled = false;
    tokio::pin!(fitting);
    let ended = loop {
        tokio::select! {
            ended = &mut fitting => break ended.unwrap_or_else(|e| Ended::Failed(WorkError {
                message: format!("the fit panicked: {e}"),
                retryable: true,
            })),
            () = tokio::time::sleep(REPORT_EVERY) => {
                let progress = *latest.borrow_and_update();
                let request = report(&id, worker, progress, started);
                match client.progress(request).await {
                    Ok(answer) if answer.get_ref().cancelled => {
                        cancelled = true;
                        stop.store(true, Ordering::Relaxed);
                    }
                    Ok(_) => {}
                    // The job is no longer this worker's (its lease ran out): stop and drop it.
                    Err(status) if status.code() == tonic::Code::InvalidArgument => {
                        tracing::warn!(job = %id, "the server dropped the job: {}", status.message());
                        stop.store(true, Ordering::Relaxed);
                    }
                    Err(status) => tracing::warn!(job = %id, "progress not reported: {}", status.message()),
                }
                if *shutdown.borrow() {
                    stop.store(true, Ordering::Relaxed);
                }
            }
        }
    };
    let answer = match ended {
        Ended::Fitted(scene, outcome) => {
            let header = pb::FinishFitRequest {
                part: Some(pb::finish_fit_request::Part::Header(pb::FinishFitHeader {
                    job_id: id.clone(),
                    worker: worker.to_owned(),
                    outcome_json: serde_json::to_string(&outcome).unwrap_or_default(),
                })),
            };
            let pieces = scene.chunks(PIECE).map(|piece| pb::FinishFitRequest {
                part: Some(pb::finish_fit_request::Part::Scene(piece.to_vec())),
            });
            let messages: Vec<_> = std::iter::once(header).chain(pieces).collect();
            client
                .finish_fit(tokio_stream::iter(messages))
                .await
                .map(|_| "fitted")
        }
        Ended::Stopped if cancelled => client
            .fail(pb::FailRequest {
                job_id: id.clone(),
                worker: worker.to_owned(),
                error: "cancelled".into(),
                retryable: false,
                cancelled: true,
            })
            .await
            .map(|_| "cancelled"),
        Ended::Stopped => client
            .release(pb::ReleaseRequest {
                job_id: id.clone(),
                worker: worker.to_owned(),
                reason: "the worker is stopping".into(),
            })
            .await
            .map(|_| "released: queued again, the attempt not counted"),
        Ended::Failed(e) => client
            .fail(pb::FailRequest {
                job_id: id.clone(),
                worker: worker.to_owned(),
                error: e.message,
                retryable: e.retryable,
                cancelled: false,
            })
            .await
            .map(|_| "failed"),
    };
    match answer {
        Ok(what) => {
            tracing::info!(job = %id, seconds = started.elapsed().as_secs_f64(), "fit {what}")
        }
        Err(status) => {
            tracing::warn!(job = %id, "the server did not take the report: {}", status.message())
        }
    }
}

/// A progress report: the fit's latest step, or "preparing" before its first.
fn report(
    id: &str,
    worker: &str,
    progress: Option<c4g_fit::Progress>,
    started: Instant,
) -> pb::ProgressRequest {
    let elapsed_s = Some(started.elapsed().as_secs_f64());
    match progress {
        None => pb::ProgressRequest {
            job_id: id.to_owned(),
            worker: worker.to_owned(),
            stage: "preparing".into(),
            elapsed_s,
            ..Default::default()
        },
        Some(p) => pb::ProgressRequest {
            job_id: id.to_owned(),
            worker: worker.to_owned(),
            step: u32::try_from(p.step).unwrap_or(u32::MAX),
            steps: u32::try_from(p.steps).unwrap_or(u32::MAX),
            stage: "fitting".into(),
            loss: Some(p.loss).filter(|l| l.is_finite()),
            holdout_psnr: p.holdout_psnr.filter(|v| v.is_finite()),
            gaussians: Some(p.gaussians as u64),
            elapsed_s,
        },
    }
}
