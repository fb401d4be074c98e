//! The worker: pulls refinement jobs from `c4g-server` (gRPC `c4g.v1.Jobs`), runs the pipeline,
//! reports progress after every denoising step (its heartbeat, and how it learns of a
//! cancellation), and sends back the refined novel views.
//!
//! A worker that dies mid-job simply stops reporting: the server's lease on the job runs out and
//! the job is retried on another attempt or failed. Nothing here has to clean up after a crash.
//!
//! A worker asked to stop (the `shutdown` channel of [`run`] turns true: the binary does so on
//! SIGTERM or Ctrl-C) drains instead: it takes no new job (a `Take` in flight is abandoned), stops
//! the job it holds at its next denoising step and hands it back (`Release`: queued again, the
//! attempt not counted), then [`run`] returns. A job that finishes before its next step is sent
//! as usual. Whatever the drain does not get to (a step longer than the binary's drain timeout, a
//! job handed over just as its `Take` was abandoned, an unreachable server) the lease takes back,
//! as after a crash.

use std::ops::ControlFlow;
use std::sync::Arc;
use std::time::{Duration, Instant};

use c4g_proto::v1 as pb;
use c4g_proto::worker::{Client, WorkerConfig, connect, stopping};
use image::RgbImage;
use image::imageops::FilterType;
use tokio::sync::watch;

use crate::layout::{self, Keyframe};
use crate::{ErrorKind, Layout, Mask, Pipeline, RefineRequest, RefinerError, Sampler};

/// How long one `Take` waits for a job before asking again.
const TAKE_WAIT: Duration = Duration::from_secs(20);
/// Pause after a failed call to the server before trying again.
const RECONNECT_PAUSE: Duration = Duration::from_secs(1);

/// Why a worker hands a job back in `Release`.
const STOPPING: &str = "the worker is stopping";

/// Runs jobs until `shutdown` turns true, then drains (see the module documentation) and
/// returns. A dropped sender never stops the worker.
pub async fn run(
    config: WorkerConfig,
    pipeline: Arc<Pipeline>,
    mut shutdown: watch::Receiver<bool>,
) -> Result<(), String> {
    let mut client = connect(&config)?;
    let m = pipeline.package().manifest();
    tracing::info!(server = %config.server, worker = %config.name, model = %m.name, "worker started");
    loop {
        if *shutdown.borrow() {
            break;
        }
        let take = client.take(pb::TakeRequest {
            worker: config.name.clone(),
            wait_ms: TAKE_WAIT.as_millis() as u32,
            frames: m.frames as u32,
            width: m.width as u32,
            height: m.height as u32,
            keyframes: m.keyframe_slots() as u32,
        });
        let take = tokio::select! {
            take = take => take,
            () = stopping(&mut shutdown) => break,
        };
        let job = match take {
            Ok(response) => response.into_inner().job,
            Err(status) if status.code() == tonic::Code::Unauthenticated => {
                return Err(format!(
                    "the server refused this worker: {}",
                    status.message()
                ));
            }
            Err(status) => {
                tracing::warn!("cannot reach the server: {}", status.message());
                tokio::select! {
                    () = tokio::time::sleep(RECONNECT_PAUSE) => continue,
                    () = stopping(&mut shutdown) => break,
                }
            }
        };
        if let Some(job) = job {
            run_job(&mut client, &config.name, &pipeline, job, &shutdown).await;
        }
    }
    tracing::info!(worker = %config.name, "worker stopped: it takes no more jobs");
    Ok(())
}

async fn run_job(
    client: &mut Client,
    worker: &str,
    pipeline: &Arc<Pipeline>,
    job: pb::RefineJob,
    shutdown: &watch::Receiver<bool>,
) {
    let id = job.job_id.clone();
    tracing::info!(job = %id, attempt = job.attempt, frames = job.frames.len(), "job started");
    let started = Instant::now();
    let outcome = refine(
        client.clone(),
        worker,
        pipeline.clone(),
        job,
        shutdown.clone(),
    )
    .await;
    let report = match outcome {
        // Stopped for the worker's own shutdown, not the server's cancellation (were it both,
        // the server cancels the job on release): the job goes back to the queue.
        Err(e) if e.kind() == ErrorKind::Cancelled && *shutdown.borrow() => {
            tracing::info!(job = %id, "stopping: handing the job back ({e})");
            client
                .release(pb::ReleaseRequest {
                    job_id: id.clone(),
                    worker: worker.to_owned(),
                    reason: STOPPING.to_owned(),
                })
                .await
                .map(|_| "released: it is queued again, the attempt not counted")
        }
        Ok(reactive) => {
            let messages = std::iter::once(pb::FinishRequest {
                part: Some(pb::finish_request::Part::Header(pb::FinishHeader {
                    job_id: id.clone(),
                    worker: worker.to_owned(),
                    frames: reactive.len() as u32,
                    seconds: started.elapsed().as_secs_f64(),
                })),
            })
            .chain(reactive.into_iter().map(|png| pb::FinishRequest {
                part: Some(pb::finish_request::Part::FramePng(png)),
            }))
            .collect::<Vec<_>>();
            client
                .finish(tokio_stream::iter(messages))
                .await
                .map(|_| "done")
        }
        Err(e) => {
            let cancelled = e.kind() == ErrorKind::Cancelled;
            // Bad input fails for good; a runtime or model failure may pass on another attempt.
            let retryable = matches!(e.kind(), ErrorKind::Runtime | ErrorKind::ModelOutput);
            client
                .fail(pb::FailRequest {
                    job_id: id.clone(),
                    worker: worker.to_owned(),
                    error: e.to_string(),
                    retryable,
                    cancelled,
                })
                .await
                .map(|_| if cancelled { "cancelled" } else { "failed" })
        }
    };
    match report {
        Ok(what) => {
            tracing::info!(job = %id, seconds = started.elapsed().as_secs_f64(), "job {what}")
        }
        // The server no longer counts this worker as the job's owner (its lease ran out, or the
        // server restarted): the job's record already says what happens next.
        Err(status) => {
            tracing::warn!(job = %id, "the server did not take the report: {}", status.message())
        }
    }
}

/// Prepares the job (frames, prompt embeddings: the text encoder may take seconds) and runs the
/// pipeline, on a blocking thread, reporting each step. Returns the regenerated frames as PNGs.
async fn refine(
    client: Client,
    worker: &str,
    pipeline: Arc<Pipeline>,
    job: pb::RefineJob,
    shutdown: watch::Receiver<bool>,
) -> Result<Vec<Vec<u8>>, RefinerError> {
    let handle = tokio::runtime::Handle::current();
    let worker = worker.to_owned();
    let (height, width) = {
        let m = pipeline.package().manifest();
        (m.height, m.width)
    };
    tokio::task::spawn_blocking(move || {
        let request = request(&pipeline, &job)?;
        let id = job.job_id;
        let mut client = client;
        let mut progress = |step: usize, steps: usize| {
            // A stopping worker ends the job here, at the first step after the signal.
            if *shutdown.borrow() {
                return ControlFlow::Break(());
            }
            let report = pb::ProgressRequest {
                job_id: id.clone(),
                worker: worker.clone(),
                step: step as u32,
                steps: steps as u32,
                stage: "denoising".into(),
                ..Default::default()
            };
            match handle.block_on(client.progress(report)) {
                Ok(answer) if answer.get_ref().cancelled => ControlFlow::Break(()),
                Ok(_) => ControlFlow::Continue(()),
                // The job is no longer ours: stop spending compute on it.
                Err(status) if status.code() == tonic::Code::InvalidArgument => {
                    ControlFlow::Break(())
                }
                // The server is unreachable for a moment: keep going; the lease decides.
                Err(_) => ControlFlow::Continue(()),
            }
        };
        let output = pipeline.refine(&request, &mut progress)?;
        // VACE's layout gives back every frame, the kept ones too; C4G's the rendered ones only.
        let regenerated: Vec<&Vec<f32>> = match &pipeline.manifest().layout {
            Layout::Vace => output
                .frames
                .iter()
                .zip(&job.reactive)
                .filter_map(|(frame, reactive)| reactive.then_some(frame))
                .collect(),
            Layout::C4g(_) => output.frames.iter().collect(),
        };
        regenerated
            .into_iter()
            .map(|frame| to_png(frame, width, height))
            .collect()
    })
    .await
    .map_err(|e| RefinerError::ModelOutput(format!("the refinement thread panicked: {e}")))?
}

/// The pipeline request for a job: frames fitted to the model's size, mask or keyframes (by the
/// package's layout), prompt, settings. Settings the job leaves out take the layout's defaults.
fn request(pipeline: &Pipeline, job: &pb::RefineJob) -> Result<RefineRequest, RefinerError> {
    let m = pipeline.package().manifest();
    if job.reactive.len() != job.frames.len() {
        return Err(RefinerError::InvalidRequest(format!(
            "the job has {} frames and {} reactive flags",
            job.frames.len(),
            job.reactive.len()
        )));
    }
    let video = job
        .frames
        .iter()
        .map(|frame| {
            let image = image::load_from_memory(&frame.png)
                .map_err(|e| {
                    RefinerError::InvalidRequest(format!("a job frame is unreadable: {e}"))
                })?
                .to_rgb8();
            Ok(to_unit(&fit(&image, m.width as u32, m.height as u32)))
        })
        .collect::<Result<Vec<_>, RefinerError>>()?;
    let tokens = job.text_tokens as usize;
    let text = prompt(
        pipeline,
        embedding(&job.text_embedding, tokens, m.text.tokens, m.text.dim)?,
        &job.caption,
    )?;
    let mut request = match &m.layout {
        Layout::Vace => {
            if job.frames.len() != m.frames {
                return Err(RefinerError::InvalidRequest(format!(
                    "the job has {} frames; this worker's model takes {}",
                    job.frames.len(),
                    m.frames
                )));
            }
            RefineRequest::new(video, Mask::Frames(job.reactive.clone()), text)
        }
        Layout::C4g(layout) => {
            // Context frames become keyframes, placed on the rendered frames' time grid.
            let times = |reactive: bool| -> Vec<f64> {
                job.frames
                    .iter()
                    .zip(&job.reactive)
                    .filter(|(_, r)| **r == reactive)
                    .map(|(f, _)| f.time)
                    .collect()
            };
            let indices = layout::source_indices(&times(false), &times(true));
            let (mut keyframes, mut rendered) = (Vec::new(), Vec::new());
            for (frame, reactive) in video.into_iter().zip(&job.reactive) {
                if *reactive {
                    rendered.push(frame);
                } else {
                    keyframes.push(frame);
                }
            }
            let keyframes = keyframes
                .into_iter()
                .zip(indices)
                .map(|(frame, source_index)| Keyframe {
                    frame,
                    source_index,
                })
                .collect();
            RefineRequest::keyframed(layout, keyframes, rendered, text)
        }
    };
    request.negative_embeddings = Some(prompt(
        pipeline,
        embedding(&job.negative_embedding, tokens, m.text.tokens, m.text.dim)?,
        &job.negative_prompt,
    )?);
    let params: serde_json::Value = serde_json::from_str(&job.params_json)
        .map_err(|e| RefinerError::InvalidRequest(format!("bad job parameters: {e}")))?;
    if let Some(steps) = params["steps"].as_u64() {
        request.steps = steps as usize;
    }
    if let Some(shift) = params["shift"].as_f64() {
        request.shift = shift;
    }
    if let Some(guidance) = params["guidance"].as_f64() {
        request.guidance = guidance as f32;
    }
    if let Some(scale) = params["control_scale"].as_f64() {
        request.control_scale = scale as f32;
    }
    if let Some(seed) = params["seed"].as_u64() {
        request.seed = seed;
    }
    match params["sampler"].as_str() {
        Some("unipc") => request.sampler = Sampler::UniPc,
        Some("euler") => request.sampler = Sampler::Euler,
        Some("diffsynth_euler") => request.sampler = Sampler::DiffSynthEuler,
        Some(other) => {
            return Err(RefinerError::InvalidRequest(format!(
                "unknown sampler {other:?} (this worker runs unipc, euler and diffsynth_euler)"
            )));
        }
        None => {}
    }
    Ok(request)
}

/// A prompt's embedding: the precomputed one if the job has it, else the text's (an error when
/// there is text and no text encoder). No text at all is the empty prompt, as in the reference
/// pipeline; without a text encoder it is all zeros.
fn prompt(
    pipeline: &Pipeline,
    precomputed: Option<Vec<f32>>,
    text: &str,
) -> Result<Vec<f32>, RefinerError> {
    match precomputed {
        Some(embedding) => Ok(embedding),
        None if !text.is_empty() || pipeline.text_encoder().is_some() => {
            pipeline.embed_caption(text)
        }
        None => Ok(vec![0.0; pipeline.manifest().text_len()]),
    }
}

/// A prompt embedding of `tokens` rows zero-padded to the model's `max_tokens` (as the reference
/// pipeline pads its text encoder's output); `None` when the job has none.
fn embedding(
    bytes: &[u8],
    tokens: usize,
    max_tokens: usize,
    dim: usize,
) -> Result<Option<Vec<f32>>, RefinerError> {
    if bytes.is_empty() {
        return Ok(None);
    }
    let values: Vec<f32> = bytes
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect();
    if tokens == 0 || tokens > max_tokens || values.len() != tokens * dim {
        return Err(RefinerError::InvalidRequest(format!(
            "the text embedding has {} numbers for {tokens} tokens; this model takes up to \
             {max_tokens} tokens of {dim}",
            values.len()
        )));
    }
    let mut padded = values;
    padded.resize(max_tokens * dim, 0.0);
    Ok(Some(padded))
}

/// The frame cropped to the model's aspect ratio about its centre, then resized (Lanczos).
fn fit(image: &RgbImage, width: u32, height: u32) -> RgbImage {
    let (w, h) = image.dimensions();
    if (w, h) == (width, height) {
        return image.clone();
    }
    let target = f64::from(width) / f64::from(height);
    let (cw, ch) = if f64::from(w) / f64::from(h) > target {
        (((f64::from(h) * target).round() as u32).clamp(1, w), h)
    } else {
        (w, ((f64::from(w) / target).round() as u32).clamp(1, h))
    };
    let cropped = image::imageops::crop_imm(image, (w - cw) / 2, (h - ch) / 2, cw, ch).to_image();
    image::imageops::resize(&cropped, width, height, FilterType::Lanczos3)
}

fn to_unit(image: &RgbImage) -> Vec<f32> {
    image
        .as_raw()
        .iter()
        .map(|v| f32::from(*v) / 255.0)
        .collect()
}

fn to_png(frame: &[f32], width: usize, height: usize) -> Result<Vec<u8>, RefinerError> {
    let bytes: Vec<u8> = frame
        .iter()
        .map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8)
        .collect();
    let image = RgbImage::from_raw(width as u32, height as u32, bytes)
        .ok_or_else(|| RefinerError::ModelOutput("a refined frame has the wrong size".into()))?;
    let mut png = Vec::new();
    image
        .write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
        .map_err(|e| RefinerError::ModelOutput(format!("PNG encoding failed: {e}")))?;
    Ok(png)
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    #[test]
    fn frames_are_centre_cropped_to_the_models_aspect_then_resized() {
        let mut image = RgbImage::new(40, 20);
        // Left and right quarters red: a 2:1 frame fitted to 1:1 keeps only the green middle.
        for (x, _, p) in image.enumerate_pixels_mut() {
            *p = if (10..30).contains(&x) {
                image::Rgb([0, 255, 0])
            } else {
                image::Rgb([255, 0, 0])
            };
        }
        let fitted = fit(&image, 8, 8);
        assert_eq!(fitted.dimensions(), (8, 8));
        assert!(
            fitted.pixels().all(|p| p[1] > 200 && p[0] < 50),
            "{fitted:?}"
        );
    }

    #[test]
    fn embeddings_are_zero_padded_and_checked() {
        let bytes: Vec<u8> = [1.0f32, 2.0, 3.0, 4.0]
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect();
        let padded = embedding(&bytes, 2, 3, 2).unwrap().unwrap();
        assert_eq!(padded, vec![1.0, 2.0, 3.0, 4.0, 0.0, 0.0]);
        assert!(embedding(&bytes, 3, 3, 2).is_err());
        assert!(embedding(&bytes, 2, 1, 2).is_err());
        assert!(embedding(&[], 0, 3, 2).unwrap().is_none());
    }
}
