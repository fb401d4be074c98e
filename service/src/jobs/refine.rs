//! Refinement requests: what a client asks for (`POST /v1/clips/{id}/refine`), checked when it
//! is submitted, and the video a worker gets when it takes the job: the clip's context frames
//! (keep) followed by novel views rendered along the requested path (regenerate), sized to the
//! worker's model and laid out as its package's layout wants: VACE's (context and novel frames
//! filling the model's frames) or C4G's (exactly the model's keyframes, then its novel frames).

use std::sync::Arc;

use c4g_scene::Trajectory;
use serde::{Deserialize, Serialize};
use serde_json::json;

use crate::ServiceError;
use crate::jobs::JobRecord;
use crate::sets::quality::QualitySpec;
use crate::views::camera::CameraSpec;
use crate::views::image_formats::{ImageFormat, encode_image, le_bytes};
use crate::views::render::{PathRequest, Views};

/// Samplers a worker runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SamplerName {
    /// UniPC, order 2 (VACE-layout workers' default: fewer steps for the same quality).
    #[default]
    Unipc,
    /// Euler on diffusers' FlowMatchEuler schedule.
    Euler,
    /// Euler on DiffSynth's schedule: what C4G's own pipeline runs (C4G-layout workers' default).
    DiffsynthEuler,
}

/// A refinement request. Every field is optional.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RefineRequest {
    /// A camera preset for the novel views (default: the first context camera, still).
    pub trajectory: Option<Trajectory>,
    /// Or explicit cameras, one per novel view.
    pub cameras: Option<Vec<CameraSpec>>,
    /// The camera a preset moves around.
    #[serde(default)]
    pub camera: CameraSpec,
    /// First time of the novel views (default: the span's start).
    pub start: Option<f64>,
    /// Last time (default: the span's end).
    pub end: Option<f64>,
    /// Context frames to condition on (default: all of the clip's, as many as fit; a C4G-layout
    /// worker takes exactly its keyframe count).
    pub context_frames: Option<usize>,
    /// A caption of the scene (the prompt), encoded by the worker's text encoder.
    pub caption: Option<String>,
    /// What the result should not look like (the negative prompt; default empty).
    pub negative_prompt: Option<String>,
    /// A precomputed prompt embedding, `[tokens, dim]` row-major.
    pub text_embedding: Option<Vec<f32>>,
    /// Its token count.
    pub text_tokens: Option<usize>,
    /// A precomputed negative-prompt embedding (same shape).
    pub negative_embedding: Option<Vec<f32>>,
    /// Denoising steps (default: the worker's layout's, 30 for VACE's and 50 for C4G's): the main
    /// speed / quality trade.
    pub steps: Option<u32>,
    /// Flow shift (default 3 for VACE's layout, 5 for C4G's).
    pub shift: Option<f64>,
    /// Classifier-free guidance (default 5; 1 skips the unconditional pass).
    pub guidance: Option<f64>,
    /// Sampler (default UniPC for VACE's layout, DiffSynth's Euler for C4G's).
    pub sampler: Option<SamplerName>,
    /// Noise seed (default 0).
    pub seed: Option<u64>,
    /// Strength of the VACE control (default 1).
    pub control_scale: Option<f64>,
    /// Frame rate of the result video (default 16).
    pub fps: Option<f64>,
}

/// Most denoising steps a request may ask for.
pub const MAX_STEPS: u32 = 1000;
/// Longest caption or negative prompt, in characters: umT5 reads 512 tokens (a few thousand
/// characters) and drops the rest, so longer text only costs the worker.
pub const MAX_PROMPT_CHARS: usize = 10_000;

impl RefineRequest {
    /// Checks everything that can be checked before a worker has the job.
    pub fn validate(&self, views: &Views, clip_id: &str) -> Result<(), ServiceError> {
        let steps = self.steps.unwrap_or(30);
        if steps == 0 || steps > MAX_STEPS {
            return Err(ServiceError::invalid(format!(
                "steps must be in 1..={MAX_STEPS}, got {steps}"
            )));
        }
        for (name, value, min) in [
            ("shift", self.shift, 0.0),
            ("guidance", self.guidance, 0.0),
            ("control_scale", self.control_scale, -1e6),
            ("fps", self.fps, 0.0),
        ] {
            if let Some(v) = value
                && !(v.is_finite() && v > min)
            {
                return Err(ServiceError::invalid(format!(
                    "{name} must be a finite number above {min}, got {v}"
                )));
            }
        }
        for (name, text, other, has_other) in [
            (
                "caption",
                &self.caption,
                "text_embedding",
                self.text_embedding.is_some(),
            ),
            (
                "negative_prompt",
                &self.negative_prompt,
                "negative_embedding",
                self.negative_embedding.is_some(),
            ),
        ] {
            let Some(text) = text else { continue };
            if has_other {
                return Err(ServiceError::invalid(format!(
                    "give {name} or {other}, not both: the embedding would win and the text be ignored"
                )));
            }
            let chars = text.chars().count();
            if chars > MAX_PROMPT_CHARS {
                return Err(ServiceError::invalid(format!(
                    "{name} has {chars} characters; at most {MAX_PROMPT_CHARS} are accepted (the text encoder reads 512 tokens)"
                )));
            }
        }
        if self.negative_embedding.is_some() && self.text_embedding.is_none() {
            return Err(ServiceError::invalid(
                "negative_embedding needs text_embedding (their token count is text_tokens)",
            ));
        }
        if let Some(e) = &self.text_embedding {
            let tokens = self.text_tokens.unwrap_or(0);
            if tokens == 0 || e.is_empty() || e.len() % tokens != 0 {
                return Err(ServiceError::invalid(format!(
                    "text_embedding holds {} numbers: give text_tokens, a divisor of that",
                    e.len()
                )));
            }
            if self
                .negative_embedding
                .as_ref()
                .is_some_and(|n| n.len() != e.len())
            {
                return Err(ServiceError::invalid(
                    "negative_embedding must have the shape of text_embedding",
                ));
            }
            if e.iter().any(|v| !v.is_finite()) {
                return Err(ServiceError::invalid("text_embedding must be finite"));
            }
        }
        if self.context_frames == Some(0) {
            return Err(ServiceError::invalid("context_frames must be at least 1"));
        }
        // The path, planned at a nominal size: a bad camera or time range fails now, not later.
        // Nominally 8 frames, or fewer where the server allows fewer sets a request: the worker's
        // own frame count is the worker's, not the client's to be refused for.
        let record = views.store.get(clip_id)?;
        let mut path = self.path(views.limits.max_times.clamp(1, 8));
        path.width = Some(16);
        path.height = Some(16);
        if !path.cameras.is_empty() {
            path.frames = None;
        }
        views.plan_path(&record, &path)?;
        Ok(())
    }

    fn path(&self, frames: usize) -> PathRequest {
        PathRequest {
            preset: self.trajectory.clone(),
            cameras: self.cameras.clone().unwrap_or_default(),
            camera: self.camera.clone(),
            frames: Some(frames),
            start: self.start,
            end: self.end,
            width: None,
            height: None,
            background: [0.0; 3],
        }
    }

    /// The sampler settings the worker gets: what the request gave, `null` for what it left to
    /// the worker (whose defaults depend on its package's layout).
    pub fn params(&self) -> serde_json::Value {
        json!({
            "steps": self.steps,
            "shift": self.shift,
            "guidance": self.guidance,
            "sampler": self.sampler,
            "seed": self.seed.unwrap_or(0),
            "control_scale": self.control_scale.unwrap_or(1.0),
        })
    }
}

/// What a worker's model takes, from its `Take`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct WorkerModel {
    /// Frames per run: context and novel frames (VACE's layout), novel frames only (C4G's).
    pub frames: usize,
    /// C4G's layout: exactly this many context frames (keyframes); 0 for VACE's layout.
    pub keyframes: usize,
    /// Frame size.
    pub width: u32,
    /// Frame size.
    pub height: u32,
}

/// A job as a worker gets it, in domain terms (the edge puts it into the `RefineJob` message).
#[derive(Debug, Clone, PartialEq)]
pub struct WorkerJob {
    /// The job.
    pub job_id: String,
    /// Which attempt this is.
    pub attempt: u32,
    /// The video, (time, PNG) per frame: context frames, then novel views.
    pub frames: Vec<(f64, Vec<u8>)>,
    /// Per frame, whether the worker regenerates it (the novel views) or keeps it.
    pub reactive: Vec<bool>,
    /// The sampler's parameters, as JSON.
    pub params_json: String,
    /// The prompt.
    pub caption: String,
    /// The negative prompt.
    pub negative_prompt: String,
    /// A precomputed prompt embedding, little-endian f32 (empty: none).
    pub text_embedding: Vec<u8>,
    /// Its token count.
    pub text_tokens: u32,
    /// A precomputed negative-prompt embedding, little-endian f32 (empty: none).
    pub negative_embedding: Vec<u8>,
}

/// The job as a worker with `model` gets it: context frames (as uploaded), then novel views
/// rendered at its size.
pub async fn build_job(
    views: &Arc<Views>,
    record: &JobRecord,
    model: WorkerModel,
) -> Result<WorkerJob, ServiceError> {
    let request: RefineRequest = serde_json::from_value(record.request.clone()).map_err(|e| {
        ServiceError::Internal(format!(
            "stored request of {} is unreadable: {e}",
            record.id
        ))
    })?;
    let clip = views.store.get_or_fetch(&record.clip_id).await?;
    let available = clip.context_times.len();
    let (context, novel) = if model.keyframes > 0 {
        // C4G's layout: exactly the model's keyframes (a clip with fewer context frames repeats
        // some), then as many novel views as the model refines.
        let k = model.keyframes;
        if request.context_frames.is_some_and(|c| c != k) {
            return Err(ServiceError::invalid(format!(
                "the worker's model takes exactly {k} context frames (its keyframes): leave context_frames out or ask for {k}"
            )));
        }
        (k, model.frames)
    } else {
        let context = request.context_frames.unwrap_or(available).min(available);
        if model.frames < context + 1 {
            return Err(ServiceError::invalid(format!(
                "the worker's model takes {} frames: too few for {context} context frames and \
                 at least one novel view (ask for fewer context_frames)",
                model.frames
            )));
        }
        (context, model.frames - context)
    };
    // The context frames spread over the clip's, first and last included.
    let chosen: Vec<usize> = (0..context)
        .map(|i| match context {
            1 => 0,
            _ => i * (available - 1) / (context - 1),
        })
        .collect();
    let mut video = Vec::with_capacity(context + novel);
    for &k in &chosen {
        video.push((
            clip.context_times[k],
            views.store.context_frame_png(&clip.id, k).await?,
        ));
    }
    let mut path = request.path(novel);
    if request.cameras.is_some() {
        path.frames = None;
    }
    path.width = Some(model.width);
    path.height = Some(model.height);
    let plan = views.plan_path(&clip, &path)?;
    // C4G's layout pads fewer novel views to the model's count (the worker drops the padding).
    let fits = match model.keyframes {
        0 => plan.len() == novel,
        _ => (1..=novel).contains(&plan.len()),
    };
    if !fits {
        return Err(ServiceError::invalid(format!(
            "{} cameras given; the worker's model refines {}{novel} novel views here",
            plan.len(),
            if model.keyframes > 0 { "1 to " } else { "" },
        )));
    }
    // Novel views over black, exact: what the worker regenerates.
    path.background = [0.0; 3];
    let rendered = views
        .render_path_all(&clip.id, &path, &QualitySpec::default(), |t, image| {
            Ok((t, encode_image(&image, ImageFormat::Png)?))
        })
        .await?;
    video.extend(rendered);
    Ok(WorkerJob {
        job_id: record.id.clone(),
        attempt: record.attempt,
        reactive: (0..video.len()).map(|i| i >= context).collect(),
        frames: video,
        params_json: request.params().to_string(),
        caption: request.caption.clone().unwrap_or_default(),
        negative_prompt: request.negative_prompt.clone().unwrap_or_default(),
        text_embedding: request
            .text_embedding
            .as_deref()
            .map(le_bytes)
            .unwrap_or_default(),
        text_tokens: request.text_tokens.unwrap_or(0) as u32,
        negative_embedding: request
            .negative_embedding
            .as_deref()
            .map(le_bytes)
            .unwrap_or_default(),
    })
}
