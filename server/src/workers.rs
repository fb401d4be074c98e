//! The gRPC service `c4g.v1.Jobs` that `c4g-refiner` workers pull refinement jobs from, and
//! `c4g-fitter` workers fit jobs (`TakeFit`, `FinishFit`; progress, failures and releases go to
//! whichever queue holds the job).

use std::sync::Arc;
use std::time::Duration;

use c4g_proto::v1 as pb;
use c4g_proto::v1::jobs_server::{Jobs, JobsServer};
use tonic::{Request, Response, Status, Streaming};

use crate::AppState;
use crate::error::{IntoStatus, status};
use c4g_service::jobs::fit::{self, FitOutcome, FitWork};
use c4g_service::jobs::refine::{WorkerJob, WorkerModel, build_job};
use c4g_service::jobs::{JobQueue, JobRecord, JobState, Progress};
use c4g_service::service::Service;
use c4g_service::{ServiceError, ServiceErrorKind};

/// Longest a worker's `Take` waits for a job.
const MAX_WAIT: Duration = Duration::from_secs(30);

/// The tonic service.
pub fn service(state: AppState) -> JobsServer<Workers> {
    let limit = state.config().limits().max_grpc_message_bytes;
    JobsServer::new(Workers { state })
        .max_decoding_message_size(limit)
        .max_encoding_message_size(usize::MAX)
}

/// Implements `c4g.v1.Jobs`.
pub struct Workers {
    state: AppState,
}

impl Workers {
    fn service(&self) -> Result<&Arc<Service>, Status> {
        self.state.service().map_err(status)
    }

    /// The next job of `queue` that `worker` can be given, waiting up to `wait` for one, as
    /// `build` makes it (`taken`: what the log says when it is handed out). `None` when none
    /// came, when the server drains (a drain also ends the wait), or when building it found the
    /// work queue full: the job then goes back as it was and the worker asks again later (an
    /// attempt spent there could fail a job for being busy). A job that cannot be built for any
    /// other reason fails (retryably when the failure is internal: nothing a worker can do about
    /// it) and the next one is taken.
    async fn take_next<W, Fut>(
        &self,
        queue: &Arc<dyn JobQueue>,
        worker: &str,
        wait: Duration,
        taken: &str,
        build: impl Fn(JobRecord) -> Fut,
    ) -> Result<Option<W>, Status>
    where
        Fut: Future<Output = Result<W, ServiceError>>,
    {
        loop {
            if self.state.is_draining() {
                return Ok(None);
            }
            let record = tokio::select! {
                record = queue.take(worker, wait) => record.map_err(status)?,
                () = self.state.drained() => None,
            };
            let Some(record) = record else {
                return Ok(None);
            };
            let (id, attempt) = (record.id.clone(), record.attempt);
            match build(record).await {
                Ok(work) => {
                    tracing::info!(job = %id, worker, attempt, "{taken}");
                    return Ok(Some(work));
                }
                Err(e)
                    if matches!(
                        e.kind(),
                        ServiceErrorKind::Overloaded | ServiceErrorKind::Busy
                    ) =>
                {
                    queue
                        .release(&id, worker, &e.to_string())
                        .await
                        .map_err(status)?;
                    return Ok(None);
                }
                Err(e) => {
                    let retryable = e.kind() == ServiceErrorKind::Internal;
                    queue
                        .fail(&id, worker, &e.to_string(), retryable, false)
                        .await
                        .map_err(status)?;
                }
            }
        }
    }
}

#[tonic::async_trait]
impl Jobs for Workers {
    async fn take(
        &self,
        request: Request<pb::TakeRequest>,
    ) -> Result<Response<pb::TakeResponse>, Status> {
        let request = request.into_inner();
        let service = self.service()?.clone();
        if request.worker.is_empty()
            || request.frames == 0
            || request.width == 0
            || request.height == 0
        {
            return Err(ServiceError::invalid(
                "a worker names itself and the frames, width and height its model refines",
            )
            .into_status());
        }
        let (w, h) = service
            .views
            .image_size(Some(request.width), Some(request.height))
            .map_err(status)?;
        let wait = Duration::from_millis(u64::from(request.wait_ms)).min(MAX_WAIT);
        let model = WorkerModel {
            frames: request.frames as usize,
            keyframes: request.keyframes as usize,
            width: w,
            height: h,
        };
        let job = self
            .take_next(
                &service.jobs,
                &request.worker,
                wait,
                "job taken",
                |record| {
                    let views = service.views.clone();
                    async move { build_job(&views, &record, model).await.map(refine_job) }
                },
            )
            .await?;
        Ok(Response::new(pb::TakeResponse { job }))
    }

    async fn progress(
        &self,
        request: Request<pb::ProgressRequest>,
    ) -> Result<Response<pb::ProgressResponse>, Status> {
        let r = request.into_inner();
        let service = self.service()?;
        let (_, queue, _) = service.find_job(&r.job_id).await.map_err(status)?;
        let cancelled = queue
            .progress(
                &r.job_id,
                &r.worker,
                Progress {
                    step: r.step,
                    steps: r.steps,
                    stage: r.stage,
                    loss: r.loss,
                    holdout_psnr: r.holdout_psnr,
                    gaussians: r.gaussians,
                    elapsed_s: r.elapsed_s,
                },
            )
            .await
            .map_err(status)?;
        Ok(Response::new(pb::ProgressResponse { cancelled }))
    }

    async fn finish(
        &self,
        request: Request<Streaming<pb::FinishRequest>>,
    ) -> Result<Response<pb::FinishResponse>, Status> {
        let service = self.service()?.clone();
        let mut stream = request.into_inner();
        let header = match stream.message().await? {
            Some(pb::FinishRequest {
                part: Some(pb::finish_request::Part::Header(h)),
            }) => h,
            _ => return Err(ServiceError::invalid("a result starts with its header").into_status()),
        };
        let mut frames = Vec::new();
        while let Some(message) = stream.message().await? {
            match message.part {
                Some(pb::finish_request::Part::FramePng(png)) => frames.push(png),
                _ => {
                    return Err(
                        ServiceError::invalid("after the header a result sends frames")
                            .into_status(),
                    );
                }
            }
        }
        if frames.len() != header.frames as usize {
            return Err(ServiceError::invalid(format!(
                "the header announced {} frames, {} came",
                header.frames,
                frames.len()
            ))
            .into_status());
        }
        if let Some(bad) = frames
            .iter()
            .position(|f| !matches!(image::guess_format(f), Ok(image::ImageFormat::Png)))
        {
            return Err(
                ServiceError::invalid(format!("result frame {bad} is not a PNG")).into_status(),
            );
        }
        let record = service
            .jobs
            .finish(&header.job_id, &header.worker, frames, header.seconds)
            .await
            .map_err(status)?;
        tracing::info!(job = %record.id, frames = record.result_frames, "job done");
        Ok(Response::new(pb::FinishResponse {}))
    }

    async fn take_fit(
        &self,
        request: Request<pb::TakeFitRequest>,
    ) -> Result<Response<pb::TakeFitResponse>, Status> {
        let request = request.into_inner();
        let service = self.service()?.clone();
        if request.worker.is_empty() {
            return Err(ServiceError::invalid("a worker names itself").into_status());
        }
        let wait = Duration::from_millis(u64::from(request.wait_ms)).min(MAX_WAIT);
        let job = self
            .take_next(
                &service.fits,
                &request.worker,
                wait,
                "fit taken",
                |record| {
                    let views = service.views.clone();
                    async move { fit::build_work(&views, &record).await.map(fit_job) }
                },
            )
            .await?;
        Ok(Response::new(pb::TakeFitResponse { job }))
    }

    async fn finish_fit(
        &self,
        request: Request<Streaming<pb::FinishFitRequest>>,
    ) -> Result<Response<pb::FinishResponse>, Status> {
        let service = self.service()?.clone();
        let limit = self.state.config().limits().max_grpc_message_bytes;
        let mut stream = request.into_inner();
        let header = match stream.message().await? {
            Some(pb::FinishFitRequest {
                part: Some(pb::finish_fit_request::Part::Header(h)),
            }) => h,
            _ => return Err(ServiceError::invalid("a result starts with its header").into_status()),
        };
        let mut scene = Vec::new();
        while let Some(message) = stream.message().await? {
            match message.part {
                Some(pb::finish_fit_request::Part::Scene(piece)) => {
                    // Bounded like one message: a fitted scene within the Gaussian bound is far
                    // smaller.
                    if scene.len() + piece.len() > limit.saturating_mul(16) {
                        return Err(ServiceError::TooLarge(
                            "the fitted scene is larger than any fit makes".into(),
                        )
                        .into_status());
                    }
                    scene.extend_from_slice(&piece);
                }
                _ => {
                    return Err(
                        ServiceError::invalid("after the header a fit sends its scene")
                            .into_status(),
                    );
                }
            }
        }
        let outcome: FitOutcome = serde_json::from_str(&header.outcome_json)
            .map_err(|e| ServiceError::invalid(format!("outcome_json: {e}")).into_status())?;
        let record = fit::complete(
            &service.views,
            service.fits.as_ref(),
            &header.job_id,
            &header.worker,
            &scene,
            outcome,
        )
        .await
        .map_err(status)?;
        tracing::info!(job = %record.id, state = ?record.state, "fit finished");
        Ok(Response::new(pb::FinishResponse {}))
    }

    async fn fail(
        &self,
        request: Request<pb::FailRequest>,
    ) -> Result<Response<pb::FailResponse>, Status> {
        let r = request.into_inner();
        let service = self.service()?;
        let (_, queue, _) = service.find_job(&r.job_id).await.map_err(status)?;
        let record = queue
            .fail(&r.job_id, &r.worker, &r.error, r.retryable, r.cancelled)
            .await
            .map_err(status)?;
        // A cancellation the client asked for is the job doing as told, not a failure.
        if record.state == JobState::Cancelled {
            tracing::info!(job = %record.id, "worker reported: {}", r.error);
        } else {
            tracing::warn!(job = %record.id, state = ?record.state, "worker reported: {}", r.error);
        }
        Ok(Response::new(pb::FailResponse {}))
    }

    async fn release(
        &self,
        request: Request<pb::ReleaseRequest>,
    ) -> Result<Response<pb::ReleaseResponse>, Status> {
        let r = request.into_inner();
        let why = if r.reason.is_empty() {
            "the worker is stopping"
        } else {
            r.reason.as_str()
        };
        // Not the job's fault: its attempt is not counted. Only the worker that holds the job may
        // hand it back (the same `drop it` answer as the other calls).
        let service = self.service()?;
        let (_, queue, _) = service.find_job(&r.job_id).await.map_err(status)?;
        let record = queue
            .release(&r.job_id, &r.worker, why)
            .await
            .map_err(status)?;
        tracing::info!(job = %record.id, worker = %r.worker, state = ?record.state, reason = why, "job released: its worker is stopping");
        Ok(Response::new(pb::ReleaseResponse {}))
    }
}

/// The work in the `FitJob` message a fit worker reads.
fn fit_job(work: FitWork) -> pb::FitJob {
    let s = &work.settings;
    let settings = serde_json::json!({
        "steps": s.steps,
        "resolution": s.resolution,
        "max_gaussians": s.max_gaussians,
        "keyframe_every": s.keyframe_every,
        "holdout_every": s.holdout_every,
        "refine_cameras": s.refine_cameras,
        "time_budget_s": s.time_budget_s,
        "seed": s.seed,
        "max_frames": s.max_frames,
    });
    pb::FitJob {
        job_id: work.job_id,
        attempt: work.attempt,
        preset: work.preset,
        settings_json: settings.to_string(),
        frames: work
            .frames
            .into_iter()
            .map(|f| pb::FitFrame {
                time: f.time,
                png: f.png,
                world_to_camera: f.world_to_camera,
                fx: f.intrinsics[0],
                fy: f.intrinsics[1],
                cx: f.intrinsics[2],
                cy: f.intrinsics[3],
            })
            .collect(),
        start: work.start,
    }
}

/// The job in the `RefineJob` message a worker reads.
fn refine_job(job: WorkerJob) -> pb::RefineJob {
    pb::RefineJob {
        job_id: job.job_id,
        attempt: job.attempt,
        frames: job
            .frames
            .into_iter()
            .map(|(time, png)| pb::VideoFrame { time, png })
            .collect(),
        reactive: job.reactive,
        params_json: job.params_json,
        caption: job.caption,
        negative_prompt: job.negative_prompt,
        text_embedding: job.text_embedding,
        text_tokens: job.text_tokens,
        negative_embedding: job.negative_embedding,
    }
}
