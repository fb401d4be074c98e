//! Jobs: [`Client::refine`] submits a refinement (`POST /v1/clips/{id}/refine`), a worker
//! process runs the video diffusion model on it, and the job's record ([`Job`]) tells where it
//! is. [`Client::job_events`] follows a job as server-sent events until it ends;
//! [`Client::job_result`] fetches the refined video. Fits ([`Client::fit`](crate::Client::fit))
//! are jobs too, of `kind` `fit`, described, followed and cancelled by the same calls.
//!
//! [`Client::refine`] takes any serialisable request, so a [`RefineRequest`] and a hand-written
//! `serde_json::Value` both work; fields the typed request leaves `None` are not sent, and the
//! server's defaults apply.

use bytes::Bytes;
use futures_util::stream::{self, BoxStream, Stream, StreamExt};
use reqwest::StatusCode;
use reqwest::header::ACCEPT;
use serde::{Deserialize, Serialize};
use serde_json::{Map, Value};

use crate::client::json;
use crate::render::CameraSpec;
use crate::sse::{SseDecoder, SseEvent};
use crate::{Client, Error};

/// A job, as `GET /v1/jobs/{id}` and every job event describe it. Fields the client does not
/// name (the request, timestamps) are kept in [`extra`](Self::extra), so a job re-serialises as
/// the server sent it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Job {
    /// The job id.
    pub id: String,
    /// `refine` or `fit` (empty from a server that does not say).
    #[serde(default, skip_serializing_if = "String::is_empty")]
    pub kind: String,
    /// The clip it refines or fits.
    #[serde(default)]
    pub clip_id: String,
    /// `queued`, `running`, `done`, `failed` or `cancelled` (see [`is_terminal`](Self::is_terminal)).
    #[serde(default)]
    pub state: String,
    /// The attempt, from 1: a job whose worker stops reporting is queued again.
    #[serde(default)]
    pub attempt: u32,
    /// Attempts allowed before the job fails.
    #[serde(default)]
    pub max_attempts: u32,
    /// The worker running it.
    #[serde(default)]
    pub worker: Option<String>,
    /// The latest progress of a running job.
    #[serde(default)]
    pub progress: Option<JobProgress>,
    /// Why it failed.
    #[serde(default)]
    pub error: Option<String>,
    /// What happened to it, oldest first (`attempt 1: worker w1 stopped responding`).
    #[serde(default)]
    pub history: Vec<String>,
    /// Refined frames stored (once a refinement is done): `?frame=k` of the result takes `k`
    /// below this. A fit's result is the clip's fitted scene instead.
    #[serde(default)]
    pub result_frames: u64,
    /// Seconds the successful attempt took on its worker.
    #[serde(default)]
    pub seconds: Option<f64>,
    /// Everything else the server reported.
    #[serde(flatten)]
    pub extra: Map<String, Value>,
}

impl Job {
    /// True in the states a job never leaves: `done`, `failed` and `cancelled`.
    pub fn is_terminal(&self) -> bool {
        matches!(self.state.as_str(), "done" | "failed" | "cancelled")
    }

    /// True once the result is stored.
    pub fn is_done(&self) -> bool {
        self.state == "done"
    }

    /// True for a fit job.
    pub fn is_fit(&self) -> bool {
        self.kind == "fit"
    }
}

/// Progress of a running job.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct JobProgress {
    /// Steps done.
    #[serde(default)]
    pub step: u32,
    /// Steps in all.
    #[serde(default)]
    pub steps: u32,
    /// What the worker is doing (a fit: `preparing`, `fitting`, `storing`).
    #[serde(default)]
    pub stage: String,
    /// A fit's loss at its latest step.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub loss: Option<f64>,
    /// A fit's mean PSNR (dB) on its held-out frames, when it last scored them.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub holdout_psnr: Option<f64>,
    /// A fit's Gaussians per keyframe now.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub gaussians: Option<u64>,
    /// Seconds the worker has spent on this attempt.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub elapsed_s: Option<f64>,
    /// Everything else the server reported.
    #[serde(flatten)]
    pub extra: Map<String, Value>,
}

/// The samplers a worker runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Sampler {
    /// UniPC, order 2 (VACE-layout workers' default: fewer steps for the same quality).
    Unipc,
    /// Euler on diffusers' schedule.
    Euler,
    /// Euler on DiffSynth's schedule, as C4G's own pipeline runs it (C4G-layout workers' default).
    DiffsynthEuler,
}

/// A refinement request, as `docs/api.md` describes its JSON. Every field is optional.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct RefineRequest {
    /// A camera preset for the novel views (default: the first context camera, still); build one
    /// with [`TrajectoryPreset::to_json`](crate::TrajectoryPreset::to_json).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub trajectory: Option<Value>,
    /// Or explicit cameras, one per novel view.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub cameras: Option<Vec<CameraSpec>>,
    /// The camera a preset moves around (default: the first context camera).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub camera: Option<CameraSpec>,
    /// First time of the novel views (default: the context span's start).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub start: Option<f64>,
    /// Last time of the novel views (default: the context span's end).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub end: Option<f64>,
    /// Context frames to condition on (default: all of the clip's, as many as fit; a C4G-layout
    /// worker takes exactly its keyframe count).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub context_frames: Option<usize>,
    /// A caption of the scene (the prompt).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub caption: Option<String>,
    /// What the result should not look like (the negative prompt).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub negative_prompt: Option<String>,
    /// A precomputed prompt embedding, `[tokens, dim]` row-major.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub text_embedding: Option<Vec<f32>>,
    /// The embedding's token count.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub text_tokens: Option<usize>,
    /// A precomputed negative-prompt embedding (same shape).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub negative_embedding: Option<Vec<f32>>,
    /// Denoising steps (default: the worker's layout's, 30 for VACE's, 50 for C4G's): the main
    /// speed / quality trade.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub steps: Option<u32>,
    /// Flow shift (default 3 for VACE's layout, 5 for C4G's).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub shift: Option<f64>,
    /// Classifier-free guidance (server default 5; 1 skips the unconditional pass).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub guidance: Option<f64>,
    /// The sampler (default UniPC for VACE's layout, DiffSynth's Euler for C4G's).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub sampler: Option<Sampler>,
    /// Noise seed (server default 0).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub seed: Option<u64>,
    /// Strength of the VACE control (server default 1).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub control_scale: Option<f64>,
    /// Frame rate of the result video (server default 16).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub fps: Option<f64>,
}

/// The records of one job as they change, ending after a terminal state; the first error ends
/// the stream.
pub type JobEvents = BoxStream<'static, Result<Job, Error>>;

impl Client {
    /// Submits a refinement of a clip (`POST /v1/clips/{id}/refine`); the server answers `202`
    /// with the queued job.
    pub async fn refine<R: Serialize + ?Sized>(
        &self,
        clip_id: &str,
        request: &R,
    ) -> Result<Job, Error> {
        let url = self.url(&["v1", "clips", clip_id, "refine"]);
        let response = self.send(self.http().post(url).json(request)).await?;
        if response.status() != StatusCode::ACCEPTED {
            return Err(Error::Malformed(format!(
                "a refinement is answered 202 Accepted, not {}",
                response.status()
            )));
        }
        json(response).await
    }

    /// Describes one job (`GET /v1/jobs/{id}`).
    pub async fn job(&self, job_id: &str) -> Result<Job, Error> {
        let url = self.url(&["v1", "jobs", job_id]);
        json(self.send(self.http().get(url)).await?).await
    }

    /// Every job the server knows (`GET /v1/jobs`).
    pub async fn jobs(&self) -> Result<Vec<Job>, Error> {
        #[derive(Deserialize)]
        struct Jobs {
            jobs: Vec<Job>,
        }
        let url = self.url(&["v1", "jobs"]);
        Ok(json::<Jobs>(self.send(self.http().get(url)).await?)
            .await?
            .jobs)
    }

    /// Cancels a job (`POST /v1/jobs/{id}/cancel`): a queued job is cancelled at once, a running
    /// one at its worker's next step. Returns the job as it is now (a running one stays
    /// `running` until its worker stops); a job already ended is left as it was.
    pub async fn cancel(&self, job_id: &str) -> Result<Job, Error> {
        let url = self.url(&["v1", "jobs", job_id, "cancel"]);
        json(self.send(self.http().post(url)).await?).await
    }

    /// Follows a job (`GET /v1/jobs/{id}/events`): its record now, then on every change, ending
    /// after a terminal state (`done`, `failed`, `cancelled`). The request is made when the
    /// stream is first polled; an error answer (an unknown job) is the stream's one item. A
    /// connection that ends before the job does is an error ([`Error::Http`] or
    /// [`Error::Interrupted`]), after which a caller may follow the job again.
    pub fn job_events(&self, job_id: &str) -> JobEvents {
        let url = self.url(&["v1", "jobs", job_id, "events"]);
        let request = self.http().get(url).header(ACCEPT, "text/event-stream");
        let client = self.clone();
        stream::once(async move { client.send(request).await })
            .flat_map(|response| match response {
                Ok(response) => job_event_stream(response.bytes_stream()),
                Err(error) => stream::iter([Err(error)]).boxed(),
            })
            .boxed()
    }

    /// The refined novel views as an MP4 (`GET /v1/jobs/{id}/result`), once the job is done.
    pub async fn job_result(&self, job_id: &str) -> Result<Bytes, Error> {
        let url = self.url(&["v1", "jobs", job_id, "result"]);
        Ok(self.send(self.http().get(url)).await?.bytes().await?)
    }

    /// One refined frame as a PNG (`GET /v1/jobs/{id}/result?frame=k`), `k` below the job's
    /// [`result_frames`](Job::result_frames).
    pub async fn job_result_frame(&self, job_id: &str, frame: u64) -> Result<Bytes, Error> {
        let mut url = self.url(&["v1", "jobs", job_id, "result"]);
        url.query_pairs_mut()
            .append_pair("frame", &frame.to_string());
        Ok(self.send(self.http().get(url)).await?.bytes().await?)
    }
}

/// Parses the body of `GET /v1/jobs/{id}/events` into job records: each `job` event's data is
/// one record; comments (keep-alives) and events of other types are skipped. The stream ends
/// after the first record in a terminal state, whatever follows it; a body that ends before
/// then ends the stream with [`Error::Interrupted`], and a record that is not a job's with
/// [`Error::Malformed`].
/// [`Client::job_events`] is this over a request; it is public so any byte source can be read.
pub fn job_event_stream<S, E>(bytes: S) -> JobEvents
where
    S: Stream<Item = Result<Bytes, E>> + Send + 'static,
    E: Into<Error>,
{
    struct State<S> {
        bytes: std::pin::Pin<Box<S>>,
        decoder: SseDecoder,
        pending: std::collections::VecDeque<SseEvent>,
        last_state: Option<String>,
        ended: bool,
    }
    let state = State {
        bytes: Box::pin(bytes),
        decoder: SseDecoder::new(),
        pending: Default::default(),
        last_state: None,
        ended: false,
    };
    stream::unfold(state, |mut st| async move {
        if st.ended {
            return None;
        }
        loop {
            while let Some(event) = st.pending.pop_front() {
                if event.event != "job" {
                    continue;
                }
                let item = match serde_json::from_str::<Job>(&event.data) {
                    Ok(job) => {
                        st.ended = job.is_terminal();
                        st.last_state = Some(job.state.clone());
                        Ok(job)
                    }
                    Err(e) => {
                        st.ended = true;
                        Err(Error::Malformed(format!("a job event is not a job: {e}")))
                    }
                };
                return Some((item, st));
            }
            match st.bytes.next().await {
                Some(Ok(chunk)) => {
                    let events = st.decoder.push(&chunk);
                    st.pending.extend(events);
                }
                Some(Err(error)) => {
                    st.ended = true;
                    return Some((Err(error.into()), st));
                }
                None => {
                    st.ended = true;
                    let last = match &st.last_state {
                        Some(state) => format!("it was last {state}"),
                        None => "no job event came".to_owned(),
                    };
                    let error = Error::Interrupted(format!(
                        "the job's event stream ended before the job did ({last})"
                    ));
                    return Some((Err(error), st));
                }
            }
        }
    })
    .boxed()
}
