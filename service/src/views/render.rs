//! [`Views`], the views layer's object, and the renders: one view of a clip at a time, and a
//! camera path frame by frame (the one trajectory render both transports and refinement jobs
//! use). The other views (`features`, `tracking`, `recovery`, `exports`, `camera_scale`) are
//! `Views` methods in their own files.

use std::sync::Arc;
use std::time::Instant;

use c4g_engine::Engine;
use c4g_renderer::Image;
use c4g_scene::{Camera, GaussianSet, Trajectory};
use tokio::sync::mpsc;

use crate::ServiceError;
use crate::clips::record::ClipRecord;
use crate::clips::store::ClipStore;
use crate::config::Limits;
use crate::sets::SetSource;
use crate::sets::quality::QualitySpec;
use crate::sets::streaming::{STREAM_AHEAD, plan_sets};
use crate::views::camera::CameraSpec;
use crate::views::feature_field::FeatureField;
use crate::views::rasterizer::Renderer;
use crate::work::WorkSlots;

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

/// What is seen of the clips: renders, feature images, tracks, exports and the cameras found by
/// rendering. Sets come from the [`SetSource`] below, records and frames from the store.
pub struct Views {
    /// The model (its input size is the default view size; its feature decoder lifts).
    pub engine: Arc<Engine>,
    /// Every clip.
    pub store: Arc<ClipStore>,
    /// Where sets come from.
    pub sets: Arc<SetSource>,
    /// The rasterizer.
    pub renderer: Renderer,
    /// Request limits.
    pub limits: Limits,
    /// Renders run here, beside the decodes.
    work: Arc<WorkSlots>,
    /// The package's feature kind and each clip's feature colouring (`crate::views::features`).
    pub(crate) features: FeatureField,
}

impl Views {
    /// The views of `sets`' clips, rendered by `renderer`.
    pub fn new(
        sets: Arc<SetSource>,
        renderer: Renderer,
        limits: Limits,
        work: Arc<WorkSlots>,
    ) -> Self {
        let engine = sets.engine.clone();
        let store = sets.store.clone();
        let features = FeatureField::of_package(engine.package().dir());
        Self {
            engine,
            store,
            sets,
            renderer,
            limits,
            work,
            features,
        }
    }

    /// Forgets what was computed of clip `id` (it was deleted): its feature colouring.
    pub fn forget(&self, id: &str) {
        self.features.forget(id);
    }

    /// Runs a decode or render on a blocking thread once a work slot is free.
    pub async fn work<T: Send + 'static>(
        self: &Arc<Self>,
        work: impl FnOnce(&Views) -> Result<T, ServiceError> + Send + 'static,
    ) -> Result<T, ServiceError> {
        let views = self.clone();
        self.work.run(move || work(&views)).await
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
        self.sets.check_times(record, &[view.t])?;
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
        let approximation = self
            .sets
            .approximation(&record, &quality, &[view.t])
            .await?;
        let encoding = self.store.encoding(id).await?;
        if approximation.is_exact() {
            let (_, set) = self
                .sets
                .exact(id, encoding, vec![view.t])
                .await?
                .pop()
                .ok_or_else(|| ServiceError::Internal("the decoder returned no set".into()))?;
            return self
                .work(move |views| views.render_now(&set, &camera, view.background))
                .await;
        }
        let id = id.to_owned();
        self.work(move |views| {
            let plan = views
                .sets
                .plan_sets_now(&id, &encoding, &[view.t], &approximation)?;
            let (_, set) = views
                .sets
                .sets_now(&plan, &encoding, &[view.t])?
                .pop()
                .ok_or_else(|| ServiceError::Internal("the decoder returned no set".into()))?;
            views.render_now(&set, &camera, view.background)
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
        self.sets.check_times(record, &[start, end])?;
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

    /// Renders the camera path `path` of clip `id` frame by frame, its sets as `quality` asks:
    /// planned once (keyframes over the whole path, pruning), then decoded and rendered a chunk of
    /// the engine's batch at a time on work slots, each frame handed to `finish` on the work
    /// thread (an image encoder, say) and sent in time order, at most
    /// [`STREAM_AHEAD`](crate::sets::streaming::STREAM_AHEAD) frames ahead of the reader. The
    /// one trajectory render: REST's video, gRPC's stream of images and a refinement job's novel
    /// views all come from here. A reader that goes away takes the rendering out of the queue, or
    /// stops it at its next frame.
    pub async fn render_path<T: Send + 'static>(
        self: &Arc<Self>,
        id: &str,
        path: &PathRequest,
        quality: &QualitySpec,
        finish: impl Fn(f64, Image) -> Result<T, ServiceError> + Send + Sync + 'static,
    ) -> Result<mpsc::Receiver<Result<T, ServiceError>>, ServiceError> {
        let record = self.store.get_or_fetch(id).await?;
        let frames = self.plan_path(&record, path)?;
        let times: Vec<f64> = frames.iter().map(|(t, _)| *t).collect();
        let approximation = self.sets.approximation(&record, quality, &times).await?;
        let encoding = self.store.encoding(id).await?;
        let plan = plan_sets(&self.sets, id, &encoding, &times, approximation).await?;
        let batch = self.engine.decode_batch_size(encoding.frame_count()).max(1);
        let (tx, rx) = mpsc::channel(STREAM_AHEAD);
        let (views, background, finish) = (self.clone(), path.background, Arc::new(finish));
        tokio::spawn(async move {
            for chunk in frames.chunks(batch) {
                let (chunk, encoding, plan) = (chunk.to_vec(), encoding.clone(), plan.clone());
                let finish = finish.clone();
                let work = views.work(move |views| {
                    let times: Vec<f64> = chunk.iter().map(|(t, _)| *t).collect();
                    let sets = views.sets.sets_now(&plan, &encoding, &times)?;
                    sets.into_iter()
                        .zip(&chunk)
                        .map(|((t, set), (_, camera))| {
                            crate::work::stop_if_cancelled()?;
                            finish(t, views.render_now(&set, camera, background)?)
                        })
                        .collect::<Result<Vec<T>, ServiceError>>()
                });
                // Dropping the work when the reader leaves takes it out of the queue, or stops
                // it at its next frame.
                let rendered = tokio::select! {
                    rendered = work => rendered,
                    () = tx.closed() => return,
                };
                match rendered {
                    Ok(items) => {
                        for item in items {
                            if tx.send(Ok(item)).await.is_err() {
                                return;
                            }
                        }
                    }
                    Err(e) => {
                        let _ = tx.send(Err(e)).await;
                        return;
                    }
                }
            }
        });
        Ok(rx)
    }

    /// Every frame [`render_path`](Self::render_path) renders, `finish`ed, in time order.
    pub async fn render_path_all<T: Send + 'static>(
        self: &Arc<Self>,
        id: &str,
        path: &PathRequest,
        quality: &QualitySpec,
        finish: impl Fn(f64, Image) -> Result<T, ServiceError> + Send + Sync + 'static,
    ) -> Result<Vec<T>, ServiceError> {
        let mut frames = self.render_path(id, path, quality, finish).await?;
        let mut all = Vec::new();
        while let Some(frame) = frames.recv().await {
            all.push(frame?);
        }
        Ok(all)
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
