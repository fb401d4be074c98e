//! [`Service`], the core's root: the loaded model, the layers (the clip store, the set source,
//! the views, the job queues), and what spans them: an upload (intake, an encode slot, the
//! encode, the scale fit of given cameras) and a delete. REST handlers and gRPC methods call
//! it and its layers.
//!
//! Encodes, decodes and renders are CPU work: they run on blocking threads, never on the async
//! runtime's, so a slow encode cannot stall health checks or streams. Encodes take one of a few
//! slots and are refused at once when all are busy (429); decodes and renders wait for a work
//! slot (`work`) in a bounded queue (503 past it), which bounds memory under load.

use std::io::Read;
use std::path::Path;
use std::sync::Arc;
use std::time::{Duration, Instant};

use c4g_engine::{ContextFrame, Engine};
use sha2::{Digest, Sha256};
use tokio::sync::Semaphore;

use crate::ServiceError;
use crate::clips::intake::cameras::{ClipCameras, Parsed};
use crate::clips::intake::kept::Keep;
use crate::clips::intake::{self, IntakeOptions, IntakeTools, Media};
use crate::clips::record::{ClipRecord, KeptFrames, now};
use crate::clips::shared::SharedClips;
use crate::clips::store::{ClipStore, NewClip};
use crate::config::{Config, Limits};
use crate::jobs::{self, JobKind, JobQueue, JobRecord};
use crate::sets::SetSource;
use crate::sets::batching::DecodeBatcher;
use crate::views::rasterizer::Renderer;
use crate::views::render::Views;
use crate::work::WorkSlots;

/// How long a client refused for lack of an encode slot should wait.
const ENCODE_RETRY_AFTER: Duration = Duration::from_secs(5);

/// The loaded service: the model and the layers of the core, and what spans them (upload,
/// delete). Each layer owns its state and uses only those below it.
pub struct Service {
    /// The model.
    pub engine: Arc<Engine>,
    /// Every clip.
    pub store: Arc<ClipStore>,
    /// The Gaussian sets of every clip at any times: what everything above asks for sets.
    pub sets: Arc<SetSource>,
    /// Request limits.
    pub limits: Limits,
    /// FFmpeg and scratch space.
    pub tools: IntakeTools,
    /// Refinement jobs: on this replica's disk, or in the database replicas share.
    pub jobs: Arc<dyn JobQueue>,
    /// Fit jobs, in a queue of their own in the same store (`crate::jobs::fit`).
    pub fits: Arc<dyn JobQueue>,
    /// Where refined videos are kept once made from a job's frames (derived: any replica can
    /// make them again).
    pub job_videos: std::path::PathBuf,
    /// What is seen of the clips: renders, feature images, tracks, exports, recovered cameras.
    pub views: Arc<Views>,
    model_key: String,
    encode_slots: Arc<Semaphore>,
    /// How many source frames each upload keeps for fits, and their long side.
    keep: Keep,
}

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
        let queue = |dir: &str, key: &str| {
            jobs::open(
                config.job_database.as_ref().map(|url| url.expose()),
                &config.store_dir.join(&model_key).join(dir),
                key,
                std::time::Duration::from_secs_f64(config.job_lease_s.max(0.1)),
                config.job_attempts,
            )
            .map_err(|e| e.to_string())
        };
        let jobs = queue("jobs", &model_key)?;
        let fits = queue("fit-jobs", &format!("{model_key}/fit"))?;
        let renderer = Renderer::new(
            config.renderer,
            config.footprint(engine.manifest().footprint()),
        )?;
        let work = Arc::new(WorkSlots::new(
            config.max_concurrent_work(),
            config.max_queued_work(),
        ));
        let (engine, store) = (Arc::new(engine), Arc::new(store));
        let batcher = Arc::new(DecodeBatcher::new(
            engine.clone(),
            work.clone(),
            config.batch_wait(),
        ));
        tracing::info!(
            renderer = renderer.name(),
            work_slots = work.capacity(),
            batch_wait_ms = batcher.wait().as_millis() as u64,
            "service ready"
        );
        let sets = Arc::new(SetSource::new(
            engine.clone(),
            store.clone(),
            limits.clone(),
            work.clone(),
            batcher,
            renderer.footprint(),
        ));
        let tools = IntakeTools::new(config.ffmpeg.clone(), config.store_dir.join("scratch"));
        let cleared = tools.clear_scratch();
        if cleared > 0 {
            tracing::info!(cleared, "scratch files of an earlier process removed");
        }
        let views = Arc::new(Views::new(sets.clone(), renderer, limits.clone(), work));
        Ok(Self {
            engine,
            store,
            sets,
            tools,
            limits,
            jobs,
            fits,
            job_videos: config.store_dir.join(&model_key).join("job-videos"),
            model_key,
            encode_slots: Arc::new(Semaphore::new(config.max_concurrent_encodes.max(1))),
            keep: Keep {
                count: config.kept_frames,
                side: config.kept_frame_side,
            },
            views,
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
        let mut intake =
            intake::read(media, &options, &self.limits, &self.tools, self.keep).await?;
        let (kept_times, kept_frames): (Vec<f64>, Vec<_>) = std::mem::take(&mut intake.kept)
            .into_iter()
            .map(|f| (f.time, f.image))
            .unzip();
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
                    service.views.fit_camera_scale(cameras, &encoding, &frames)
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
                kept_frames: kept_frames.first().map(|first| KeptFrames {
                    times: kept_times,
                    width: first.width(),
                    height: first.height(),
                }),
            },
            encoding,
            frames,
            kept_frames,
        })
    }

    /// Deletes clip `id`: its record, features and frames, what pruning measured of it and its
    /// feature colouring.
    pub async fn delete(&self, id: &str) -> Result<(), ServiceError> {
        self.store.delete(id).await?;
        self.sets.forget(id);
        self.views.forget(id);
        Ok(())
    }

    /// Job `id` (a refinement or a fit) and the queue that holds it.
    pub async fn find_job(
        &self,
        id: &str,
    ) -> Result<(JobKind, &Arc<dyn JobQueue>, JobRecord), ServiceError> {
        match self.jobs.get(id).await {
            Ok(record) => Ok((JobKind::Refine, &self.jobs, record)),
            Err(e) if e.kind() == crate::ServiceErrorKind::NotFound => {
                Ok((JobKind::Fit, &self.fits, self.fits.get(id).await?))
            }
            Err(e) => Err(e),
        }
    }

    /// The short hash of the model package that keys its clips and jobs on disk.
    pub fn model_key(&self) -> &str {
        &self.model_key
    }
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
