//! Fit jobs: what a client asks for (`POST /v1/clips/{id}/fit`), checked when it is submitted;
//! the work a fit worker gets when it takes the job (the clip's kept source frames at their input
//! cameras, and the feed-forward sets at the keyframe times to start from); and what its result
//! becomes (the clip's fitted scene, [`crate::clips::fitted`]).
//!
//! Fit jobs live in their own queue of the job store (`Service::fits`: on disk beside the
//! refinement jobs, or the same PostgreSQL table under the model key with `/fit` appended), so a
//! refinement worker never takes a fit and a fit worker never takes a refinement, and every
//! queue's guarantees (leases, attempts, cancellation, a follower on any replica) hold for both.
//!
//! A fit's result is stored only while its worker still holds the job and no cancellation was
//! asked for: a cancelled, failed or superseded fit leaves the clip's earlier fitted scene (and
//! always its feed-forward scene) as they were.

use std::sync::Arc;

use c4g_fit::{FitSettings, FittedScene, Preset};
use serde::{Deserialize, Serialize};

use crate::ServiceError;
use crate::clips::fitted::{Fitted, FittedSummary};
use crate::clips::intake::cameras::input_camera;
use crate::clips::record::{ClipRecord, now};
use crate::jobs::{JobQueue, JobRecord};
use crate::sets::quality::QualitySpec;
use crate::sets::scene::Scene;
use crate::views::render::Views;

/// A fit request. Every field is optional: the preset's value stands for a field left out.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FitRequest {
    /// `fast` (about a minute on two cores), `default` (about five) or `best`.
    pub preset: Option<String>,
    /// Optimisation steps (one training frame each).
    pub steps: Option<u64>,
    /// Long side of the working frames, pixels (at most the kept frames').
    pub resolution: Option<u32>,
    /// Most Gaussians per keyframe: densification grows the scene up to it.
    pub max_gaussians: Option<usize>,
    /// A keyframe every this many kept source frames between the context times (0: the context
    /// times alone).
    pub keyframe_every: Option<usize>,
    /// Every this-many-th frame is held out and scored, never trained on (0: none).
    pub holdout_every: Option<usize>,
    /// Refine the input cameras jointly.
    pub refine_cameras: Option<bool>,
    /// Stop after this many seconds, wherever the steps are.
    pub time_budget_s: Option<f64>,
    /// Seeds the frame order and densification: the same seed, the same fit.
    pub seed: Option<u64>,
    /// Most source frames to supervise with.
    pub max_frames: Option<usize>,
}

impl FitRequest {
    /// The preset and the settings it resolves to, checked.
    pub fn settings(&self) -> Result<(Preset, FitSettings), ServiceError> {
        let preset = match self.preset.as_deref() {
            None => Preset::Default,
            Some(name) => Preset::parse(name).ok_or_else(|| {
                ServiceError::invalid(format!(
                    "preset must be \"fast\", \"default\" or \"best\", got {}",
                    crate::quoted(name)
                ))
            })?,
        };
        let base = preset.settings();
        let settings = FitSettings {
            steps: self.steps.unwrap_or(base.steps),
            resolution: self.resolution.unwrap_or(base.resolution),
            max_gaussians: self.max_gaussians.unwrap_or(base.max_gaussians),
            keyframe_every: self.keyframe_every.unwrap_or(base.keyframe_every),
            holdout_every: self.holdout_every.unwrap_or(base.holdout_every),
            refine_cameras: self.refine_cameras.unwrap_or(base.refine_cameras),
            time_budget_s: self.time_budget_s.or(base.time_budget_s),
            seed: self.seed.unwrap_or(base.seed),
            max_frames: self.max_frames.unwrap_or(base.max_frames),
        };
        settings
            .check()
            .map_err(|e| ServiceError::invalid(e.to_string()))?;
        Ok((preset, settings))
    }
}

/// One frame a fit supervises with.
#[derive(Debug, Clone, PartialEq)]
pub struct FitFrame {
    /// Seconds, the clip's clock.
    pub time: f64,
    /// The frame (PNG), at the size it was kept.
    pub png: Vec<u8>,
    /// Its input camera: row-major 4×4 world-to-camera (OpenCV axes, the model's frame)...
    pub world_to_camera: Vec<f64>,
    /// ...and intrinsics `[fx, fy, cx, cy]` as fractions of the model's square centre crop of
    /// the frame (given cameras, which state fractions of the whole frame, are converted; the
    /// worker maps them onto the whole frame at its working size).
    pub intrinsics: [f64; 4],
}

/// What a fit worker gets when it takes a job.
#[derive(Debug, Clone, PartialEq)]
pub struct FitWork {
    /// The job.
    pub job_id: String,
    /// Its attempt.
    pub attempt: u32,
    /// The preset's name.
    pub preset: String,
    /// The settings, resolved.
    pub settings: FitSettings,
    /// The frames in time order.
    pub frames: Vec<FitFrame>,
    /// The feed-forward sets at the keyframe times (`c4g_fit::file`'s bytes): the start.
    pub start: Vec<u8>,
}

/// What a worker reports with its fitted scene.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FitOutcome {
    /// Steps taken.
    pub steps: u64,
    /// Seconds the fit took.
    pub seconds: f64,
    /// Held-out frame indices among the job's frames.
    pub holdout_frames: Vec<usize>,
    /// Mean held-out PSNR of the start (the feed-forward scene).
    pub holdout_psnr_before: Option<f64>,
    /// Mean held-out PSNR of the fitted scene.
    pub holdout_psnr_after: Option<f64>,
    /// Mean PSNR of the training frames, fitted.
    pub train_psnr: f64,
    /// Stopped before its steps (time budget).
    pub stopped: bool,
    /// Working resolution (width, height).
    pub resolution: [u32; 2],
    /// The share of the frame that stayed still, when every training frame had one camera
    /// (`c4g_fit::FitReport::still_share`; absent from workers older than it).
    #[serde(default)]
    pub still_share: Option<f64>,
}

/// Queues a fit of clip `record` as `request` asks (checked).
pub async fn submit(
    fits: &dyn JobQueue,
    record: &ClipRecord,
    request: &FitRequest,
) -> Result<JobRecord, ServiceError> {
    request.settings()?;
    let stored = serde_json::to_value(request)
        .map_err(|e| ServiceError::Internal(format!("cannot keep a fit request: {e}")))?;
    fits.create(&record.id, stored).await
}

/// The work of fit job `job` for a worker: the clip's kept frames (or its context frames, for a
/// clip stored before frames were kept) and the feed-forward sets at the keyframe times.
pub async fn build_work(views: &Arc<Views>, job: &JobRecord) -> Result<FitWork, ServiceError> {
    let request: FitRequest = serde_json::from_value(job.request.clone())
        .map_err(|e| ServiceError::invalid(format!("the stored fit request is unreadable: {e}")))?;
    let (preset, settings) = request.settings()?;
    let record = views.store.get_or_fetch(&job.clip_id).await?;
    let (times, paths) = match &record.kept_frames {
        Some(kept) => (
            kept.times.clone(),
            (0..kept.times.len())
                .map(|k| views.store.kept_frame_path(&record.id, k))
                .collect(),
        ),
        None => (
            record.context_times.clone(),
            (0..record.context_times.len())
                .map(|k| views.store.frame_path(&record.id, k))
                .collect::<Vec<_>>(),
        ),
    };
    let chosen = spread(times.len(), settings.max_frames);
    let cameras = views.input_cameras(&record);
    let mut frames = Vec::with_capacity(chosen.len());
    for k in chosen {
        let png = std::fs::read(&paths[k]).map_err(|e| {
            let error = ServiceError::Internal(format!("cannot read a kept frame: {e}"));
            views.store.unless_gone(&record.id, error)
        })?;
        let camera = input_camera(cameras.as_ref(), times[k]);
        let i = camera.intrinsics;
        let given = cameras.as_ref().is_some_and(|c| c.format != "recovered");
        let i = if given {
            i.frame_to_crop(record.source.width, record.source.height)
        } else {
            i
        };
        frames.push(FitFrame {
            time: times[k],
            png,
            world_to_camera: camera.world_to_camera,
            intrinsics: [i.fx, i.fy, i.cx, i.cy],
        });
    }
    let frame_times: Vec<f64> = frames.iter().map(|f| f.time).collect();
    let keyframes = c4g_fit::keyframe_times(&record.context_times, &frame_times, {
        // `keyframe_every` counts kept frames; the frames chosen may be sparser.
        settings.keyframe_every
    });
    let feed_forward = QualitySpec {
        scene: Scene::FeedForward,
        ..QualitySpec::default()
    };
    let sets = views
        .sets
        .decode(&record.id, keyframes, feed_forward)
        .await?;
    let start = FittedScene::new(sets).map_err(|e| {
        ServiceError::Internal(format!("the feed-forward keyframes make no scene: {e}"))
    })?;
    Ok(FitWork {
        job_id: job.id.clone(),
        attempt: job.attempt,
        preset: preset.name().to_owned(),
        settings,
        frames,
        start: c4g_fit::file::to_bytes(&start),
    })
}

/// Keeps a worker's fitted scene (`scene`: `c4g_fit::file`'s bytes) as the clip's, then marks the
/// job done; refused, keeping nothing, unless `worker` still holds the job and no cancellation
/// was asked for (the job is then cancelled). The scene must be finite and keyed as the job's
/// start was.
pub async fn complete(
    views: &Arc<Views>,
    fits: &dyn JobQueue,
    job_id: &str,
    worker: &str,
    scene: &[u8],
    outcome: FitOutcome,
) -> Result<JobRecord, ServiceError> {
    let job = fits.get(job_id).await?;
    let scene = c4g_fit::file::from_bytes(scene)
        .map_err(|e| ServiceError::invalid(format!("the fitted scene is unreadable: {e}")))?;
    let (preset, settings) = serde_json::from_value::<FitRequest>(job.request.clone())
        .map_err(|e| ServiceError::invalid(format!("the stored fit request is unreadable: {e}")))?
        .settings()?;
    if scene.len() > settings.max_gaussians.max(1) {
        return Err(ServiceError::invalid(format!(
            "the fitted scene holds {} Gaussians, over the job's budget of {}",
            scene.len(),
            settings.max_gaussians
        )));
    }
    let record = views.store.get_or_fetch(&job.clip_id).await?;
    let (first, last) = record.span();
    let inside = |t: f64| first - 1e-9 <= t && t <= last + 1e-9;
    if !scene.times.iter().all(|&t| inside(t)) {
        return Err(ServiceError::invalid(
            "the fitted scene's keyframes leave the clip's span",
        ));
    }
    // Still this worker's, and not cancelled: the progress call says both (and renews the lease
    // for the write below).
    let progress = crate::jobs::Progress {
        step: u32::try_from(outcome.steps).unwrap_or(u32::MAX),
        steps: u32::try_from(settings.steps).unwrap_or(u32::MAX),
        stage: "storing".into(),
        ..Default::default()
    };
    if fits.progress(job_id, worker, progress).await? {
        return fits.fail(job_id, worker, "cancelled", false, true).await;
    }
    let frame_times = fit_frame_times(&record, &settings);
    let holdout_times = outcome
        .holdout_frames
        .iter()
        .filter_map(|&k| frame_times.get(k).copied())
        .collect();
    let summary = FittedSummary {
        job_id: job_id.to_owned(),
        preset: preset.name().to_owned(),
        gaussians: scene.len(),
        static_gaussians: scene.static_mask.iter().filter(|s| **s).count(),
        keyframes: scene.times.clone(),
        steps: outcome.steps,
        seconds: outcome.seconds,
        frames: frame_times.len(),
        resolution: outcome.resolution,
        holdout_frames: outcome.holdout_frames,
        holdout_times,
        holdout_psnr: outcome.holdout_psnr_after,
        holdout_psnr_feed_forward: outcome.holdout_psnr_before,
        train_psnr: outcome.train_psnr,
        stopped_early: outcome.stopped,
        created_at: now(),
        notes: notes(outcome.still_share, views.input_cameras(&record).is_some()),
    };
    let fitted = Fitted::new(summary, scene)?;
    views.sets.fitted.put(&record.id, fitted).await?;
    fits.finish(job_id, worker, Vec::new(), outcome.seconds)
        .await
}

/// A fitted clip whose frames stayed still over less than this share of the frame is noted as
/// probably filmed by a moving camera (measured: bedroom's handheld pan 2 %, dog's tripod 60 %;
/// a tripod on a scene that moves everywhere can fall under it too, so the note says "if").
const STILL_SHARE_OF_A_STILL_CAMERA: f64 = 0.10;

/// What the fitted scene's record says beside its numbers: for a clip without cameras (fitted at
/// the still camera) whose frames hardly stay still anywhere (`still_share`), that a moving
/// camera would have been taken for the scene's motion, and what to do about it.
fn notes(still_share: Option<f64>, has_cameras: bool) -> Vec<String> {
    match still_share {
        Some(share) if !has_cameras && share < STILL_SHARE_OF_A_STILL_CAMERA => vec![format!(
            "only {:.0} % of the frame stayed still over the clip, which has no cameras and was \
             fitted as if filmed from a still camera: if the camera moved, the fit took its \
             motion for the scene's, and renders away from the input camera will not hold; \
             upload the clip with its cameras (docs/api.md, \"Given cameras\") and fit again",
            100.0 * share
        )],
        _ => Vec::new(),
    }
}

/// The times of the frames a fit of `record` under `settings` supervises with, in order (its kept
/// frames, or its context frames when it keeps none, spread to `max_frames`): what
/// [`build_work`] sends and what a worker's frame indices refer to.
fn fit_frame_times(record: &ClipRecord, settings: &FitSettings) -> Vec<f64> {
    let times = record
        .kept_frames
        .as_ref()
        .map_or(&record.context_times, |kept| &kept.times);
    spread(times.len(), settings.max_frames)
        .into_iter()
        .map(|i| times[i])
        .collect()
}

/// `k` of `n` indices spread evenly, first and last included (all of them when `k ≥ n`).
fn spread(n: usize, k: usize) -> Vec<usize> {
    if k >= n || n <= 1 {
        return (0..n).collect();
    }
    if k <= 1 {
        return vec![0];
    }
    let mut picked: Vec<usize> = (0..k)
        .map(|i| (i * (n - 1) + (k - 1) / 2) / (k - 1))
        .collect();
    picked.dedup();
    picked
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    #[test]
    fn a_camera_less_clip_that_hardly_stays_still_is_noted_as_probably_moving() {
        // Bedroom's handheld pan kept 2 % still; dog's tripod 60 %.
        let note = notes(Some(0.02), false);
        assert_eq!(note.len(), 1);
        assert!(
            note[0].starts_with("only 2 % of the frame stayed still"),
            "{}",
            note[0]
        );
        assert!(
            note[0].contains("Given cameras"),
            "says what to do: {}",
            note[0]
        );
        assert!(notes(Some(0.60), false).is_empty(), "a tripod shot");
        assert!(
            notes(Some(0.02), true).is_empty(),
            "its cameras were given or recovered"
        );
        assert!(
            notes(None, false).is_empty(),
            "frames from more than one camera"
        );
        // A worker older than the field sends no share: its outcome still reads.
        let outcome: FitOutcome = serde_json::from_value(serde_json::json!({
            "steps": 1, "seconds": 1.0, "holdout_frames": [], "holdout_psnr_before": null,
            "holdout_psnr_after": null, "train_psnr": 20.0, "stopped": false, "resolution": [8, 8]
        }))
        .unwrap();
        assert_eq!(outcome.still_share, None);
    }

    #[test]
    fn a_request_takes_its_preset_and_overrides_and_refuses_what_is_out_of_bounds() {
        let (preset, settings) = FitRequest::default().settings().unwrap();
        assert_eq!(
            (preset, settings),
            (Preset::Default, Preset::Default.settings())
        );
        let fast = FitRequest {
            preset: Some("fast".into()),
            steps: Some(7),
            ..Default::default()
        };
        let (preset, settings) = fast.settings().unwrap();
        assert_eq!((preset, settings.steps), (Preset::Fast, 7));
        let bad = FitRequest {
            preset: Some("quick".into()),
            ..Default::default()
        };
        assert!(bad.settings().unwrap_err().to_string().contains("\"fast\""));
        let huge = FitRequest {
            steps: Some(u64::MAX),
            ..Default::default()
        };
        assert!(huge.settings().is_err());
    }

    #[test]
    fn spread_keeps_the_ends_and_never_repeats() {
        assert_eq!(spread(10, 3), vec![0, 5, 9]);
        assert_eq!(spread(3, 10), vec![0, 1, 2]);
        assert_eq!(spread(1, 1), vec![0]);
        assert_eq!(spread(0, 4), Vec::<usize>::new());
    }
}
