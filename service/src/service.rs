//! What the service does, whatever the transport: upload, decode, render. REST handlers and
//! gRPC methods both translate into these calls.
//!
//! Encodes, decodes and renders are CPU work: they run on blocking threads, never on the async
//! runtime's, so a slow encode cannot stall health checks or streams. Encodes take one of a few
//! slots and are refused at once when all are busy (429); decodes and renders wait for a work
//! slot (`work`) in a bounded queue (503 past it), which bounds memory under load.

use std::io::Read;
use std::path::Path;
use std::sync::Arc;
use std::time::{Duration, Instant};

use c4g_engine::{
    ContextFrame, Encoding, Engine, EngineError, KeyframeTrack, Keyframes, QuerySubset,
};
use c4g_renderer::Image;
use c4g_scene::{Camera, GaussianSet, Trajectory};
use sha2::{Digest, Sha256};
use tokio::sync::Semaphore;

use crate::ServiceError;
use crate::clips::intake::cameras::{ClipCameras, Parsed};
use crate::clips::intake::{self, IntakeOptions, IntakeTools, Media};
use crate::clips::record::{ClipRecord, now};
use crate::clips::shared::SharedClips;
use crate::clips::store::{ClipStore, NewClip};
use crate::config::{Config, Limits};
use crate::jobs::{self, JobQueue};
use crate::sets::batching::DecodeBatcher;
use crate::sets::pruning::Analyses;
use crate::sets::quality::{self, Approximation, QualitySpec};
use crate::views::camera::CameraSpec;
use crate::views::features::FeatureField;
use crate::views::rasterizer::Renderer;
use crate::work::WorkSlots;

/// How long a client refused for lack of an encode slot should wait.
const ENCODE_RETRY_AFTER: Duration = Duration::from_secs(5);

/// The loaded service: the model, the clip store, the rasterizer and the limits.
pub struct Service {
    /// The model.
    pub engine: Engine,
    /// Every clip.
    pub store: ClipStore,
    /// The rasterizer.
    pub renderer: Renderer,
    /// Request limits.
    pub limits: Limits,
    /// FFmpeg and scratch space.
    pub tools: IntakeTools,
    /// Refinement jobs: on this replica's disk, or in the database replicas share.
    pub jobs: Arc<dyn JobQueue>,
    /// Where refined videos are kept once made from a job's frames (derived: any replica can
    /// make them again).
    pub job_videos: std::path::PathBuf,
    model_key: String,
    encode_slots: Arc<Semaphore>,
    work: WorkSlots,
    analyses: Analyses,
    /// The package's feature kind and each clip's feature colouring (`crate::views::features`).
    pub(crate) features: FeatureField,
    /// Exact decodes of one clip gathered into shared decoder runs.
    pub(crate) batcher: DecodeBatcher,
}

/// A render of one camera at one time.
#[derive(Debug, Clone)]
pub struct ViewRequest {
    /// Media time, seconds.
    pub t: f64,
    /// The camera (default: the first context camera).
    pub camera: CameraSpec,
    /// Image width (default: the model's input width).
    pub width: Option<u32>,
    /// Image height (default: the model's input height).
    pub height: Option<u32>,
    /// Background RGB.
    pub background: [f32; 3],
}

/// A camera path over a time range.
#[derive(Debug, Clone, Default)]
pub struct PathRequest {
    /// A preset around `camera`…
    pub preset: Option<Trajectory>,
    /// …or explicit cameras, one per frame.
    pub cameras: Vec<CameraSpec>,
    /// The camera a preset moves around.
    pub camera: CameraSpec,
    /// Frames (default 24, or the number of explicit cameras).
    pub frames: Option<usize>,
    /// First time (default: the span's start).
    pub start: Option<f64>,
    /// Last time (default: the span's end).
    pub end: Option<f64>,
    /// Image width.
    pub width: Option<u32>,
    /// Image height.
    pub height: Option<u32>,
    /// Background RGB.
    pub background: [f32; 3],
}

/// Frames of a trajectory when a request does not say.
pub const DEFAULT_PATH_FRAMES: usize = 24;

impl Service {
    /// Builds the service around a loaded engine.
    pub fn new(engine: Engine, config: &Config) -> Result<Self, String> {
        let model_key = model_key(&engine).map_err(|e| format!("cannot hash the model: {e}"))?;
        let limits = config.limits();
        let mut store = ClipStore::open(
            &config.store_dir,
            &model_key,
            config.cache_mib.saturating_mul(1 << 20),
        )
        .map_err(|e| e.to_string())?;
        if let Some(url) = &config.shared_store {
            let shared = SharedClips::open(url, &model_key).map_err(|e| e.to_string())?;
            // Another replica's encode takes what an encode here would: the intake's time limit.
            store = store.with_shared(shared, limits.intake_timeout.saturating_mul(2));
        }
        let jobs = jobs::open(
            config.job_database.as_ref().map(|url| url.expose()),
            &config.store_dir.join(&model_key).join("jobs"),
            &model_key,
            std::time::Duration::from_secs_f64(config.job_lease_s.max(0.1)),
            config.job_attempts,
        )
        .map_err(|e| e.to_string())?;
        let renderer = Renderer::new(
            config.renderer,
            config.footprint(engine.manifest().footprint()),
        )?;
        let work = WorkSlots::new(config.max_concurrent_work(), config.max_queued_work());
        let batcher = DecodeBatcher::new(config.batch_wait());
        tracing::info!(
            renderer = renderer.name(),
            work_slots = work.capacity(),
            batch_wait_ms = batcher.wait().as_millis() as u64,
            "service ready"
        );
        let features = FeatureField::of_package(engine.package().dir());
        Ok(Self {
            engine,
            store,
            renderer,
            tools: IntakeTools::new(config.ffmpeg.clone(), config.store_dir.join("scratch")),
            limits,
            jobs,
            job_videos: config.store_dir.join(&model_key).join("job-videos"),
            model_key,
            encode_slots: Arc::new(Semaphore::new(config.max_concurrent_encodes.max(1))),
            work,
            analyses: Analyses::default(),
            features,
            batcher,
        })
    }

    /// Stores (encoding once) an upload; `true` when this call created the clip.
    pub async fn upload(
        self: &Arc<Self>,
        media: Media,
        options: IntakeOptions,
    ) -> Result<(Arc<ClipRecord>, bool), ServiceError> {
        // Cameras are read before anything else: a bad camera file costs no encode slot.
        let cameras = options.cameras.as_ref().map(|c| c.parse()).transpose()?;
        let id = intake::clip_id(&self.model_key, &media, &options);
        self.store
            .get_or_create(&id, || self.encode(id.clone(), media, options, cameras))
            .await
    }

    async fn encode(
        self: &Arc<Self>,
        id: String,
        media: Media,
        options: IntakeOptions,
        cameras: Option<Parsed>,
    ) -> Result<NewClip, ServiceError> {
        let slot = self.encode_slots.clone().try_acquire_owned().map_err(|_| {
            metrics::counter!("c4g_rejected_total", "reason" => "encodes_busy").increment(1);
            ServiceError::Busy {
                retry_after: ENCODE_RETRY_AFTER,
            }
        })?;
        let started = Instant::now();
        let intake = intake::read(media, &options, &self.limits, &self.tools).await?;
        metrics::histogram!("c4g_intake_duration_seconds").record(started.elapsed().as_secs_f64());
        let sources: Vec<usize> = intake.frames.iter().map(|f| f.source_index).collect();
        if let Some(parsed) = &cameras {
            let source = &intake.source;
            parsed.check_against(source.frames, source.width, source.height)?;
        }
        let service = self.clone();
        let source = intake.source.clone();
        let frame_step = intake.frame_step;
        let (encoding, frames, cameras) = tokio::task::spawn_blocking(move || {
            // Held by the encode itself: one whose client left still runs, and still counts.
            let _slot = slot;
            let started = Instant::now();
            let context = intake
                .frames
                .iter()
                .map(|f| {
                    Ok(ContextFrame::new(
                        f.time,
                        service.engine.preprocess(&f.image)?,
                    ))
                })
                .collect::<Result<Vec<_>, ServiceError>>()?;
            crate::faults::pause("encode");
            let encoding = service
                .engine
                .encode(&context)?
                .with_frame_step(frame_step)?;
            metrics::histogram!("c4g_encode_duration_seconds")
                .record(started.elapsed().as_secs_f64());
            let frames: Vec<_> = intake.frames.into_iter().map(|f| f.image).collect();
            let cameras = cameras
                .map(|parsed| {
                    // The encoding's order is time order; `frame_order` says which intake frame
                    // each is.
                    let given: Vec<_> = encoding
                        .frame_order()
                        .iter()
                        .map(|&k| parsed.cameras[sources[k]])
                        .collect();
                    let cameras =
                        ClipCameras::new(&given, encoding.times(), parsed.format, parsed.notes);
                    service.fit_camera_scale(cameras, &encoding, &frames)
                })
                .transpose()?;
            Ok::<_, ServiceError>((encoding, frames, cameras))
        })
        .await
        .map_err(|e| ServiceError::Internal(format!("encoding panicked: {e}")))??;
        tracing::info!(clip = %id, frames = encoding.frame_count(), "clip encoded");
        Ok(NewClip {
            record: ClipRecord {
                id,
                model: self.engine.manifest().name.clone(),
                created_at: now(),
                options,
                source,
                context_times: encoding.times().to_vec(),
                frame_order: encoding.frame_order().to_vec(),
                feature_shape: encoding.shape(),
                frame_step,
                cameras,
            },
            encoding,
            frames,
        })
    }

    /// Runs a decode or render on a blocking thread once a work slot is free.
    pub async fn work<T: Send + 'static>(
        self: &Arc<Self>,
        work: impl FnOnce(&Service) -> Result<T, ServiceError> + Send + 'static,
    ) -> Result<T, ServiceError> {
        let service = self.clone();
        self.work.run(move || work(&service)).await
    }

    /// Checks that `times` can be decoded for `record`: finite, inside the context span, not
    /// too many.
    pub fn check_times(&self, record: &ClipRecord, times: &[f64]) -> Result<(), ServiceError> {
        if times.is_empty() {
            return Err(ServiceError::invalid(
                "give at least one time (\"t\" or \"times\")",
            ));
        }
        if times.len() > self.limits.max_times {
            return Err(ServiceError::TooLarge(format!(
                "{} times in one request; at most {} (C4G_MAX_TIMES)",
                times.len(),
                self.limits.max_times
            )));
        }
        let (first, last) = record.span();
        for &t in times {
            if !t.is_finite() {
                return Err(ServiceError::invalid(format!(
                    "times must be finite numbers of seconds, got {t}"
                )));
            }
            if t < first || t > last {
                return Err(ServiceError::invalid(format!(
                    "t = {t} s is outside the clip's context span [{first}, {last}] s: the model \
                     interpolates between its context frames and does not extrapolate"
                )));
            }
        }
        Ok(())
    }

    /// The approximation a request over `times` of clip `record` asks for, checked (by
    /// default: exact). Presets space their keyframes by the clip's context spacing.
    pub fn approximation(
        &self,
        record: &ClipRecord,
        spec: &QualitySpec,
        times: &[f64],
    ) -> Result<Approximation, ServiceError> {
        let spacing = quality::context_spacing(&record.context_times);
        let approximation = quality::resolve(spec, times, self.limits.max_times, spacing)?;
        // Refused before any work is spent: the package's decoder cannot drop queries.
        if approximation.drop_queries && !self.engine.has_query_subset() {
            return Err(EngineError::NoQuerySubset {
                package: self.engine.manifest().name.clone(),
            }
            .into());
        }
        Ok(approximation)
    }

    /// The Gaussians of clip `id` at each time: decoded exactly, or approximated as `quality`
    /// asks (keyframes, pruning).
    pub async fn decode(
        self: &Arc<Self>,
        id: &str,
        times: Vec<f64>,
        quality: QualitySpec,
    ) -> Result<Vec<(f64, GaussianSet)>, ServiceError> {
        let record = self.store.get_or_fetch(id).await?;
        self.check_times(&record, &times)?;
        let approximation = self.approximation(&record, &quality, &times)?;
        let encoding = self.store.encoding(id).await?;
        if approximation.is_exact() {
            return self.batcher.decode(self, id, encoding, times).await;
        }
        let id = id.to_owned();
        self.work(move |service| {
            let kept = service.kept_now(&id, &encoding, &approximation)?;
            let sets = service.decode_keyframed_now(
                &encoding,
                &times,
                &approximation.keyframes,
                kept.queries.as_ref(),
            )?;
            kept.select(sets)
        })
        .await
    }

    /// Decodes on the calling (blocking) thread.
    pub fn decode_now(
        &self,
        encoding: &Encoding,
        times: &[f64],
    ) -> Result<Vec<(f64, GaussianSet)>, ServiceError> {
        self.decode_keyframed_now(encoding, times, &Keyframes::Exact, None)
    }

    /// Decodes on the calling (blocking) thread, exactly or through `keyframes`, on the queries
    /// `queries` alone when given.
    pub fn decode_keyframed_now(
        &self,
        encoding: &Encoding,
        times: &[f64],
        keyframes: &Keyframes,
        queries: Option<&QuerySubset>,
    ) -> Result<Vec<(f64, GaussianSet)>, ServiceError> {
        let started = Instant::now();
        let (sets, stats) = self
            .engine
            .decode_keyframed_on(encoding, times, keyframes, queries)?;
        metrics::histogram!("c4g_decode_duration_seconds").record(started.elapsed().as_secs_f64());
        self.record_resident();
        count_sets(stats.exact_decodes, stats.interpolated);
        Ok(times.iter().copied().zip(sets).collect())
    }

    /// Which Gaussians of clip `id` a request pruned by `prune` keeps (`None`: all of them),
    /// measuring the clip on the calling thread the first time.
    pub fn keep_now(
        &self,
        id: &str,
        encoding: &Encoding,
        prune: Option<&c4g_analysis::pruning::PruneOptions>,
    ) -> Result<Option<Vec<bool>>, ServiceError> {
        prune
            .map(|options| {
                self.analyses.keep(
                    id,
                    &self.engine,
                    encoding,
                    self.renderer.footprint(),
                    options,
                )
            })
            .transpose()
    }

    /// What a request approximated by `approximation` keeps of clip `id`: which Gaussians, and,
    /// when it drops queries, the queries its decodes run (measuring the clip on the calling
    /// thread the first time).
    pub fn kept_now(
        &self,
        id: &str,
        encoding: &Encoding,
        approximation: &Approximation,
    ) -> Result<Kept, ServiceError> {
        let keep = self.keep_now(id, encoding, approximation.prune.as_ref())?;
        let queries = match &keep {
            Some(keep) if approximation.drop_queries => Some(QuerySubset::from_mask(keep)?),
            _ => None,
        };
        Ok(Kept { keep, queries })
    }

    /// Decides, on the calling thread, where the sets of a multi-time request over `times`
    /// come from (keyframes decoded now, or the decoder set by set) and which Gaussians they
    /// keep, so that [`sets_now`](Self::sets_now) can serve them piece by piece.
    pub fn plan_sets_now(
        &self,
        id: &str,
        encoding: &Encoding,
        times: &[f64],
        approximation: &Approximation,
    ) -> Result<SetPlan, ServiceError> {
        let kept = self.kept_now(id, encoding, approximation)?;
        let track = if approximation.keyframes.interpolates(times) {
            let keyframes = &approximation.keyframes;
            Some(self.keyframe_track_now(encoding, times, keyframes, kept.queries.as_ref())?)
        } else {
            None
        };
        Ok(SetPlan { track, kept })
    }

    /// The sets at `times` as `plan` says (on the calling thread).
    pub fn sets_now(
        &self,
        plan: &SetPlan,
        encoding: &Encoding,
        times: &[f64],
    ) -> Result<Vec<(f64, GaussianSet)>, ServiceError> {
        let sets = match &plan.track {
            Some(track) => self.interpolate_now(track, times)?,
            None => self.decode_keyframed_now(
                encoding,
                times,
                &Keyframes::Exact,
                plan.kept.queries.as_ref(),
            )?,
        };
        plan.kept.select(sets)
    }

    /// Decodes the keyframes `keyframes` chooses for `times` (on the calling thread; on the
    /// queries `queries` alone when given), for [`interpolate_now`](Self::interpolate_now) to
    /// serve the sets from piece by piece.
    pub fn keyframe_track_now(
        &self,
        encoding: &Encoding,
        times: &[f64],
        keyframes: &Keyframes,
        queries: Option<&QuerySubset>,
    ) -> Result<KeyframeTrack, ServiceError> {
        let started = Instant::now();
        let (track, stats) = self
            .engine
            .keyframe_track_on(encoding, times, keyframes, queries)?;
        metrics::histogram!("c4g_decode_duration_seconds").record(started.elapsed().as_secs_f64());
        self.record_resident();
        count_sets(stats.exact_decodes, 0);
        Ok(track)
    }

    /// The sets at `times` from a track's keyframes: exact at a keyframe, else interpolated.
    pub fn interpolate_now(
        &self,
        track: &KeyframeTrack,
        times: &[f64],
    ) -> Result<Vec<(f64, GaussianSet)>, ServiceError> {
        let sets = times
            .iter()
            .map(|&t| Ok((t, track.at(t)?)))
            .collect::<Result<Vec<_>, ServiceError>>()?;
        let interpolated = times.iter().filter(|&&t| track.keyframe(t).is_none());
        count_sets(0, interpolated.count());
        Ok(sets)
    }

    /// The device-resident encodings' gauges (nothing when residency is off).
    fn record_resident(&self) {
        if let Some(stats) = self.engine.resident_stats() {
            metrics::gauge!("c4g_device_cache_bytes").set(stats.bytes as f64);
            metrics::gauge!("c4g_device_cache_clips").set(stats.encodings as f64);
            metrics::counter!("c4g_device_cache_placements_total").absolute(stats.placements);
            metrics::counter!("c4g_device_cache_spills_total").absolute(stats.spills);
        }
    }

    /// The image size a request asks for, checked against the limits.
    pub fn image_size(
        &self,
        width: Option<u32>,
        height: Option<u32>,
    ) -> Result<(u32, u32), ServiceError> {
        let input = &self.engine.manifest().input;
        let (w, h) = (width.unwrap_or(input.width), height.unwrap_or(input.height));
        if w == 0 || h == 0 {
            return Err(ServiceError::invalid(format!(
                "image size {w}x{h} must be at least 1x1"
            )));
        }
        let max = self.limits.max_side;
        if w > max || h > max || u64::from(w) * u64::from(h) > self.limits.max_render_pixels {
            return Err(ServiceError::TooLarge(format!(
                "image size {w}x{h} is over the limit: sides up to {max} (C4G_MAX_SIDE), {} \
                 pixels in all (C4G_MAX_RENDER_PIXELS)",
                self.limits.max_render_pixels
            )));
        }
        Ok((w, h))
    }

    /// The camera of a single view of clip `record`, the view checked (its time inside the span,
    /// its size within the limits, its background finite) before any decoding is spent on it.
    pub fn view_camera(
        &self,
        record: &ClipRecord,
        view: &ViewRequest,
    ) -> Result<Camera, ServiceError> {
        self.check_times(record, &[view.t])?;
        let (w, h) = self.image_size(view.width, view.height)?;
        let cameras = self.input_cameras_for(record, [&view.camera]);
        let camera = view
            .camera
            .resolve(cameras.as_ref(), view.t, None)?
            .camera(w, h)?;
        check_background(view.background)?;
        Ok(camera)
    }

    /// Renders one view of clip `id`.
    pub async fn render_view(
        self: &Arc<Self>,
        id: &str,
        view: ViewRequest,
        quality: QualitySpec,
    ) -> Result<Image, ServiceError> {
        let record = self.store.get_or_fetch(id).await?;
        let camera = self.view_camera(&record, &view)?;
        let approximation = self.approximation(&record, &quality, &[view.t])?;
        let encoding = self.store.encoding(id).await?;
        if approximation.is_exact() {
            let (_, set) = self
                .batcher
                .decode(self, id, encoding, vec![view.t])
                .await?
                .pop()
                .ok_or_else(|| ServiceError::Internal("the decoder returned no set".into()))?;
            return self
                .work(move |service| service.render_now(&set, &camera, view.background))
                .await;
        }
        let id = id.to_owned();
        self.work(move |service| {
            let plan = service.plan_sets_now(&id, &encoding, &[view.t], &approximation)?;
            let (_, set) = service
                .sets_now(&plan, &encoding, &[view.t])?
                .pop()
                .ok_or_else(|| ServiceError::Internal("the decoder returned no set".into()))?;
            service.render_now(&set, &camera, view.background)
        })
        .await
    }

    /// Renders on the calling (blocking) thread.
    pub fn render_now(
        &self,
        set: &GaussianSet,
        camera: &Camera,
        background: [f32; 3],
    ) -> Result<Image, ServiceError> {
        let started = Instant::now();
        let image = self.renderer.render(set, camera, background)?;
        metrics::histogram!("c4g_render_duration_seconds").record(started.elapsed().as_secs_f64());
        Ok(image)
    }

    /// The (time, camera) of every frame of a path, checked.
    pub fn plan_path(
        &self,
        record: &ClipRecord,
        path: &PathRequest,
    ) -> Result<Vec<(f64, Camera)>, ServiceError> {
        let (w, h) = self.image_size(path.width, path.height)?;
        check_background(path.background)?;
        let n = match (&path.preset, path.cameras.is_empty()) {
            (Some(_), false) => {
                return Err(ServiceError::invalid(
                    "give a trajectory preset or explicit cameras, not both",
                ));
            }
            (None, false) => {
                if path.frames.is_some_and(|n| n != path.cameras.len()) {
                    return Err(ServiceError::invalid(
                        "with explicit cameras the frame count is the number of cameras",
                    ));
                }
                path.cameras.len()
            }
            (_, true) => {
                let frames = path.frames.unwrap_or(DEFAULT_PATH_FRAMES);
                if frames == 0 || frames > self.limits.max_times {
                    return Err(ServiceError::invalid(format!(
                        "frames must be between 1 and {} (C4G_MAX_TIMES), got {frames}",
                        self.limits.max_times
                    )));
                }
                frames
            }
        };
        let (first, last) = record.span();
        let (start, end) = (path.start.unwrap_or(first), path.end.unwrap_or(last));
        self.check_times(record, &[start, end])?;
        let fraction = |i: usize| {
            if n == 1 {
                0.0
            } else {
                i as f64 / (n - 1) as f64
            }
        };
        let times: Vec<f64> = (0..n)
            .map(|i| match n {
                1 => start,
                // The last frame is at `end` exactly: rounding must not step outside the span.
                _ if i == n - 1 => end,
                _ => (start + (end - start) * fraction(i)).min(end),
            })
            .collect();
        let given = self.input_cameras_for(record, path.cameras.iter().chain([&path.camera]));
        let resolve = |spec: &CameraSpec, i: usize| {
            spec.resolve(given.as_ref(), times[i], Some(fraction(i)))?
                .camera(w, h)
        };
        let cameras = if path.cameras.is_empty() {
            if path.camera.follows_frames() {
                // Centred on the input camera at each frame's time: frame i of the preset built
                // around that frame's reference.
                (0..n)
                    .map(|i| {
                        let reference = resolve(&path.camera, i)?;
                        match &path.preset {
                            Some(preset) => preset
                                .cameras(&reference, n)?
                                .get(i)
                                .copied()
                                .ok_or_else(|| {
                                    ServiceError::Internal("a preset gave too few cameras".into())
                                }),
                            None => Ok(reference),
                        }
                    })
                    .collect::<Result<Vec<_>, ServiceError>>()?
            } else {
                let reference = resolve(&path.camera, 0)?;
                match &path.preset {
                    Some(preset) => preset.cameras(&reference, n)?,
                    None => vec![reference; n],
                }
            }
        } else {
            (0..n)
                .map(|i| resolve(&path.cameras[i], i))
                .collect::<Result<Vec<_>, _>>()?
        };
        Ok(times.into_iter().zip(cameras).collect())
    }

    /// Renders every frame of a planned path of clip `id`, its sets decoded exactly or
    /// approximated (keyframes decoded in one batch, pruning).
    pub fn render_path_now(
        &self,
        id: &str,
        encoding: &Encoding,
        path: &[(f64, Camera)],
        background: [f32; 3],
        approximation: &Approximation,
    ) -> Result<Vec<Image>, ServiceError> {
        let times: Vec<f64> = path.iter().map(|(t, _)| *t).collect();
        let kept = self.kept_now(id, encoding, approximation)?;
        let keyframes = &approximation.keyframes;
        let sets = self.decode_keyframed_now(encoding, &times, keyframes, kept.queries.as_ref())?;
        kept.select(sets)?
            .iter()
            .zip(path)
            .map(|((_, set), (_, camera))| {
                crate::work::stop_if_cancelled()?;
                self.render_now(set, camera, background)
            })
            .collect()
    }

    /// Deletes clip `id`: its record, features and frames, what pruning measured of it and its
    /// feature colouring.
    pub async fn delete(&self, id: &str) -> Result<(), ServiceError> {
        self.store.delete(id).await?;
        self.analyses.forget(id);
        self.features.forget(id);
        Ok(())
    }

    /// The clip's context frame `index` (upload order) as PNG bytes.
    pub async fn context_frame_png(&self, id: &str, index: usize) -> Result<Vec<u8>, ServiceError> {
        let record = self.store.get_or_fetch(id).await?;
        if index >= record.context_times.len() {
            return Err(ServiceError::NotFound(format!(
                "clip {id} has {} context frames (0..{})",
                record.context_times.len(),
                record.context_times.len()
            )));
        }
        let mut bytes = Vec::new();
        std::fs::File::open(self.store.frame_path(id, index))
            .and_then(|mut f| f.read_to_end(&mut bytes))
            .map_err(|e| ServiceError::Internal(format!("cannot read a context frame: {e}")))?;
        Ok(bytes)
    }

    /// The short hash of the model package that keys its clips and jobs on disk.
    pub fn model_key(&self) -> &str {
        &self.model_key
    }
}

/// What a request keeps of a clip's Gaussians ([`Service::kept_now`]).
pub struct Kept {
    /// The Gaussians kept (`None`: all).
    keep: Option<Vec<bool>>,
    /// The queries decodes run when the request drops queries (`None`: all of them, the
    /// Gaussians outside `keep` then removed from each decoded set).
    queries: Option<QuerySubset>,
}

impl Kept {
    /// The kept Gaussians of `sets`: sets decoded on the kept queries hold nothing else.
    pub(crate) fn select(
        &self,
        sets: Vec<(f64, GaussianSet)>,
    ) -> Result<Vec<(f64, GaussianSet)>, ServiceError> {
        if self.queries.is_some() {
            return Ok(sets);
        }
        prune(self.keep.as_deref(), sets)
    }
}

/// Where the sets of a multi-time request come from, and which Gaussians they keep: decided once
/// ([`Service::plan_sets_now`]), then served piece by piece ([`Service::sets_now`]).
pub struct SetPlan {
    /// The keyframes to interpolate from (`None`: every set decoded exactly).
    track: Option<KeyframeTrack>,
    /// The Gaussians kept, and the queries decoded.
    kept: Kept,
}

impl SetPlan {
    /// The Gaussians (of those kept) that never move, when keyframes show it: interpolation
    /// between keyframes that agree gives the same values. `None` for an exact plan.
    pub fn static_mask(&self, options: &c4g_formats::c4gv::EncodeOptions) -> Option<Vec<bool>> {
        let track = self.track.as_ref()?;
        // Keyframes decoded on the kept queries hold the kept Gaussians only.
        let keep = self
            .kept
            .keep
            .as_ref()
            .filter(|_| self.kept.queries.is_none());
        let sets: Vec<GaussianSet> = match keep {
            Some(keep) => track
                .sets()
                .iter()
                .map(|set| set.select(keep))
                .collect::<Result<_, _>>()
                .ok()?,
            None => track.sets().to_vec(),
        };
        crate::sets::streaming::static_mask(&sets, options)
    }
}

/// The Gaussians of each set that `keep` keeps (all of them without it).
fn prune(
    keep: Option<&[bool]>,
    sets: Vec<(f64, GaussianSet)>,
) -> Result<Vec<(f64, GaussianSet)>, ServiceError> {
    let Some(keep) = keep else {
        return Ok(sets);
    };
    sets.into_iter()
        .map(|(t, set)| Ok((t, set.select(keep)?)))
        .collect()
}

/// Counts the sets the decoder computed and those interpolated between keyframes.
pub(crate) fn count_sets(exact: usize, interpolated: usize) {
    for (how, n) in [("exact", exact), ("interpolated", interpolated)] {
        if n > 0 {
            metrics::counter!("c4g_decoded_sets_total", "how" => how).increment(n as u64);
        }
    }
}

pub(crate) fn check_background(background: [f32; 3]) -> Result<(), ServiceError> {
    // The renderer's own check, run before any decoding is spent on the request.
    let options = c4g_renderer::RenderOptions {
        background,
        ..c4g_renderer::RenderOptions::default()
    };
    Ok(options.validate()?)
}

/// A short hash of the package's manifest and graphs: clips are stored per model.
fn model_key(engine: &Engine) -> std::io::Result<String> {
    let package = engine.package();
    let mut hasher = Sha256::new();
    let mut files = vec![
        package.dir().join("model.json"),
        package.encoder_path(),
        package.decoder_path(),
    ];
    files.extend(package.feature_decoder_path());
    for file in files {
        hash_file(&mut hasher, &file)?;
    }
    Ok(hex::encode(&hasher.finalize()[..8]))
}

fn hash_file(hasher: &mut Sha256, path: &Path) -> std::io::Result<()> {
    let mut file = std::fs::File::open(path)?;
    let mut buffer = vec![0u8; 1 << 20];
    loop {
        let n = file.read(&mut buffer)?;
        if n == 0 {
            return Ok(());
        }
        hasher.update(&buffer[..n]);
    }
}
