//! Jobs over REST: `POST /v1/clips/{id}/refine` and `POST /v1/clips/{id}/fit` (202 with a job),
//! `GET /v1/jobs`, `GET /v1/jobs/{id}`, progress as server-sent events (`/events`), a
//! refinement's result (`/result`: MP4, or one frame as PNG with `?frame=k`; a fit's result is the
//! clip's fitted scene), and cancellation. Every job shows its `kind`: `refine` or `fit`.

use std::convert::Infallible;

use axum::Json;
use axum::extract::{RawQuery, State};
use axum::http::{StatusCode, header};
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::{IntoResponse, Response};
use futures_util::Stream;
use serde_json::{Value, json};

use super::json::{self, ClipId, JobId, JsonBody};
use crate::AppState;
use crate::error::ErrorReply;
use c4g_service::ServiceError;
use c4g_service::jobs::fit::{self, FitRequest};
use c4g_service::jobs::refine::RefineRequest;
use c4g_service::jobs::{JobKind, JobRecord, JobState};
use c4g_service::quoted;
use c4g_service::views::image_formats::encode_mp4;

pub async fn submit(
    State(state): State<AppState>,
    ClipId(clip_id): ClipId,
    JsonBody(body): JsonBody<Value>,
) -> Result<Response, ErrorReply> {
    let service = state.service()?;
    json::check_body(&body, service.limits.max_times)?;
    let request: RefineRequest = json::typed(body)?;
    check(&request, service.limits.max_context_frames)?;
    // Held here (fetched from the shared store when another replica has it) before it is checked.
    service.store.get_or_fetch(&clip_id).await?;
    request.validate(&service.views, &clip_id)?;
    let stored = serde_json::to_value(&request)
        .map_err(|e| ServiceError::Internal(format!("cannot store the request: {e}")))?;
    let record = service.jobs.create(&clip_id, stored).await?;
    Ok(accepted(JobKind::Refine, &record))
}

/// `POST /v1/clips/{id}/fit`: a fit job for the clip (`c4g_service::jobs::fit`).
pub async fn submit_fit(
    State(state): State<AppState>,
    ClipId(clip_id): ClipId,
    JsonBody(body): JsonBody<Value>,
) -> Result<Response, ErrorReply> {
    let service = state.service()?;
    json::check_body(&body, service.limits.max_times)?;
    let request: FitRequest = json::typed(body)?;
    let clip = service.store.get_or_fetch(&clip_id).await?;
    let record = fit::submit(service.fits.as_ref(), &clip, &request).await?;
    Ok(accepted(JobKind::Fit, &record))
}

/// 202 with the job and where to follow it.
fn accepted(kind: JobKind, record: &JobRecord) -> Response {
    let location = format!("/v1/jobs/{}", record.id);
    (
        StatusCode::ACCEPTED,
        [(header::LOCATION, location)],
        Json(job_json(kind, record)),
    )
        .into_response()
}

/// A job as the API shows it: its record and its kind.
fn job_json(kind: JobKind, record: &JobRecord) -> Value {
    let mut value = json!(record);
    value["kind"] = json!(kind.name());
    value
}

/// What `openapi.json` states of a refinement request that neither [`json::check_body`] nor
/// [`RefineRequest::validate`] checks: a positive token count, and no more context frames than
/// a clip can have.
fn check(request: &RefineRequest, max_context_frames: usize) -> Result<(), ServiceError> {
    if request.text_tokens == Some(0) {
        return Err(ServiceError::invalid("text_tokens must be at least 1"));
    }
    if let Some(n) = request.context_frames
        && n > max_context_frames
    {
        return Err(ServiceError::invalid(format!(
            "context_frames must be at most {max_context_frames} (C4G_MAX_CONTEXT_FRAMES), got {n}"
        )));
    }
    Ok(())
}

pub async fn list(State(state): State<AppState>) -> Result<Json<Value>, ErrorReply> {
    let service = state.service()?;
    let mut jobs: Vec<(JobKind, JobRecord)> = service
        .jobs
        .list()
        .await?
        .into_iter()
        .map(|r| (JobKind::Refine, r))
        .collect();
    jobs.extend(
        service
            .fits
            .list()
            .await?
            .into_iter()
            .map(|r| (JobKind::Fit, r)),
    );
    jobs.sort_by(|(_, a), (_, b)| (a.created_at, &a.id).cmp(&(b.created_at, &b.id)));
    let jobs: Vec<Value> = jobs.iter().map(|(k, r)| job_json(*k, r)).collect();
    Ok(Json(json!({ "jobs": jobs })))
}

pub async fn get(
    State(state): State<AppState>,
    JobId(id): JobId,
) -> Result<Json<Value>, ErrorReply> {
    let (kind, _, record) = state.service()?.find_job(&id).await?;
    Ok(Json(job_json(kind, &record)))
}

pub async fn cancel(
    State(state): State<AppState>,
    JobId(id): JobId,
) -> Result<Json<Value>, ErrorReply> {
    let (kind, queue, _) = state.service()?.find_job(&id).await?;
    Ok(Json(job_json(kind, &queue.cancel(&id).await?)))
}

/// Every change of the job as an SSE `job` event (the whole record), ending after a terminal
/// state.
pub async fn events(
    State(state): State<AppState>,
    JobId(id): JobId,
) -> Result<Sse<impl Stream<Item = Result<Event, Infallible>>>, ErrorReply> {
    let (kind, queue, _) = state.service()?.find_job(&id).await?;
    let mut updates = queue.subscribe(&id).await?;
    let drained = state.drained();
    // A draining server ends its event streams (the job goes on; a client follows it again, on
    // another replica): they could otherwise hold the drain until its deadline.
    let stream = async_stream(move |tx| async move {
        tokio::pin!(drained);
        loop {
            let record = updates.borrow_and_update().clone();
            let event = Event::default()
                .event("job")
                .json_data(job_json(kind, &record))
                .unwrap_or_default();
            if tx.send(Ok(event)).await.is_err() || record.state.is_terminal() {
                return;
            }
            tokio::select! {
                changed = updates.changed() => {
                    if changed.is_err() {
                        return;
                    }
                }
                () = &mut drained => return,
            }
        }
    });
    Ok(Sse::new(stream).keep_alive(KeepAlive::default()))
}

/// A stream fed by a task through a channel (bounded: a slow client slows the feed).
fn async_stream<F, Fut>(body: F) -> impl Stream<Item = Result<Event, Infallible>>
where
    F: FnOnce(tokio::sync::mpsc::Sender<Result<Event, Infallible>>) -> Fut,
    Fut: std::future::Future<Output = ()> + Send + 'static,
{
    let (tx, rx) = tokio::sync::mpsc::channel(16);
    tokio::spawn(body(tx));
    tokio_stream::wrappers::ReceiverStream::new(rx)
}

/// `?frame=k`: one refined frame; other query parameters are ignored.
fn result_frame(query: Option<&str>) -> Result<Option<usize>, ServiceError> {
    let mut frame = None;
    for (name, value) in json::query_pairs(query)? {
        if name == "frame" {
            frame = Some(json::decimal(&value).ok_or_else(|| {
                ServiceError::invalid(format!(
                    "frame must be a refined frame's index (0, 1, ...), got {value_quoted}",
                    value_quoted = quoted(&value)
                ))
            })?);
        }
    }
    Ok(frame)
}

pub async fn result(
    State(state): State<AppState>,
    JobId(id): JobId,
    RawQuery(query): RawQuery,
) -> Result<Response, ErrorReply> {
    let frame = result_frame(query.as_deref())?;
    let service = state.service()?.clone();
    let (kind, _, record) = service.find_job(&id).await?;
    if kind == JobKind::Fit {
        return Err(ServiceError::NotFound(format!(
            "job {id} is a fit: its result is the clip's fitted scene (GET /v1/clips/{}; \
             renders and decodes serve it)",
            record.clip_id
        ))
        .into());
    }
    if record.state != JobState::Done {
        return Err(ServiceError::invalid(format!(
            "job {id} is {}: its result exists once it is done (GET /v1/jobs/{id})",
            record.state.name()
        ))
        .into());
    }
    if let Some(k) = frame {
        if k >= record.result_frames {
            return Err(ServiceError::NotFound(format!(
                "job {id} has {} refined frames (0..{})",
                record.result_frames, record.result_frames
            ))
            .into());
        }
        let png = service.jobs.result_frame(&id, k).await?;
        return Ok(([(header::CONTENT_TYPE, "image/png")], png).into_response());
    }
    // The video is made from the frames once per replica, and kept (derived: when it cannot
    // be kept, it is made again next time).
    let video = service.job_videos.join(format!("{id}.mp4"));
    if let Ok(mp4) = tokio::fs::read(&video).await {
        return Ok(([(header::CONTENT_TYPE, "video/mp4")], mp4).into_response());
    }
    let mut frames = Vec::new();
    let (mut width, mut height) = (0, 0);
    for k in 0..record.result_frames {
        let png = service.jobs.result_frame(&id, k).await?;
        let image = image::load_from_memory(&png)
            .map_err(|e| ServiceError::Internal(format!("a result frame is unreadable: {e}")))?
            .to_rgb8();
        (width, height) = image.dimensions();
        frames.push(image.into_raw());
    }
    let fps = record.request["fps"].as_f64().unwrap_or(16.0);
    let mp4 = encode_mp4(
        &service.tools.ffmpeg,
        &service.tools.scratch,
        &frames,
        width,
        height,
        fps,
    )
    .await?;
    let (dir, kept) = (service.job_videos.clone(), mp4.clone());
    let keep = tokio::task::spawn_blocking(move || -> std::io::Result<()> {
        use std::io::Write;
        std::fs::create_dir_all(&dir)?;
        // A temporary file of this request's own, renamed: two requests may make it at once.
        let mut file = tempfile::Builder::new().prefix(".").tempfile_in(&dir)?;
        file.write_all(&kept)?;
        file.persist(&video).map_err(|e| e.error)?;
        Ok(())
    })
    .await;
    if let Ok(Err(e)) = keep {
        tracing::warn!(job = %id, "cannot keep the result video: {e}");
    }
    Ok(([(header::CONTENT_TYPE, "video/mp4")], mp4).into_response())
}
