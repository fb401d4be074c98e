//! Recovered cameras: each context frame's camera found by photometric alignment of the model's
//! own Gaussians, for clips uploaded without cameras (C4G predicts none).
//!
//! Frame by frame in time order, the set decoded exactly at the frame's time is rendered and its
//! camera moved until the render matches the frame as the model saw it (centre-cropped and
//! resized to the model's input): `c4g_analysis::align_camera`, Levenberg–Marquardt on an
//! analytic camera Jacobian over a coarse-to-fine pyramid with an alpha-weighted Huber loss.
//! The first context camera is the model's frame itself (the identity, by C4G's convention), so
//! it is not moved; each later frame starts from the previous frame's solution, as a video's
//! camera moves little between frames.
//!
//! With `refine_focal`, the focal length is one for the clip: a first pass refines a focal scale
//! with each frame's pose (the first frame's too, whose pose is then set back to the identity),
//! the clip's focal is the median of those frames' estimates weighted by nothing (a confident
//! outlier should not win), and a second pass refines the poses alone at that focal.
//!
//! The result is kept beside the clip (`recovered-cameras.json` in its directory, written
//! synced and renamed into place), shown by `GET /v1/clips/{id}` with each frame's residuals and
//! confidence, and used as the input camera (renders' `{"input": …}` cameras and tracks) of a
//! clip that has no given cameras. It is derived data: any replica can recover it again.

use std::path::Path;
use std::sync::Arc;

use c4g_analysis::{AlignOptions, Alignment};
use c4g_engine::preprocess::{crop_and_resize, decode_frame};
use c4g_scene::{Camera, GaussianSet, NormalizedIntrinsics};
use glam::{Affine3A, Mat4};
use image::RgbImage;
use serde::{Deserialize, Serialize};

use crate::ServiceError;
use crate::clips::durable::{sync_dir, write_synced};
use crate::clips::intake::cameras::{ClipCameras, ContextCamera, Intrinsics};
use crate::clips::record::ClipRecord;
use crate::views::camera::CameraSpec;
use crate::views::render::Views;

/// The file beside a clip's record.
const FILE: &str = "recovered-cameras.json";

/// What a recovery may vary.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RecoverOptions {
    /// Refine one focal length for the clip as well as each frame's pose.
    #[serde(default)]
    pub refine_focal: bool,
}

/// A clip's recovered cameras.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RecoveredCameras {
    /// The cameras, as given cameras are stored (`format` "recovered", `scale` 1: the model's
    /// own units).
    pub cameras: ClipCameras,
    /// How each was found, in the same order.
    pub fits: Vec<FrameFit>,
    /// The options they were recovered with.
    pub options: RecoverOptions,
}

/// How one context frame's camera was found.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct FrameFit {
    /// The frame's time, seconds.
    pub t: f64,
    /// Mean robust residual per colour channel at the starting camera (`align_camera`'s).
    pub initial_residual: f64,
    /// The same at the recovered camera.
    pub residual: f64,
    /// How far to trust the camera, 0 to 1 (coverage × fit × conditioning).
    pub confidence: f64,
    /// Mean rendered alpha at the recovered camera.
    pub coverage: f64,
    /// Smallest over largest eigenvalue of the normalised Gauss–Newton matrix.
    pub conditioning: f64,
    /// Levenberg–Marquardt steps.
    pub iterations: usize,
    /// Whether the finest level stopped by its tolerance.
    pub converged: bool,
}

impl Views {
    /// Recovers the cameras of clip `id`'s context frames and keeps them with the clip.
    pub async fn recover_cameras(
        self: &Arc<Self>,
        id: &str,
        options: RecoverOptions,
    ) -> Result<RecoveredCameras, ServiceError> {
        let record = self.store.get_or_fetch(id).await?;
        let times = record.context_times.clone();
        // The model's own scene: a fitted one was fitted at the input cameras recovered here.
        let feed_forward = crate::sets::quality::QualitySpec {
            scene: crate::sets::scene::Scene::FeedForward,
            ..Default::default()
        };
        let sets = self.sets.decode(id, times, feed_forward).await?;
        let owned = id.to_owned();
        self.work(move |views| {
            let targets = (0..record.context_times.len())
                .map(|k| views.model_view(&owned, k))
                .collect::<Result<Vec<_>, _>>()?;
            let recovered = views.align_frames(&record, &sets, &targets, options)?;
            views.keep_recovered(&owned, &recovered)?;
            Ok(recovered)
        })
        .await
        // Its frames read, or its cameras kept, after a delete: the clip is gone, not broken.
        .map_err(|e| self.store.unless_gone(id, e))
    }

    /// The recovered cameras kept with clip `id`, if any.
    pub fn recovered_cameras(&self, id: &str) -> Option<RecoveredCameras> {
        let bytes = std::fs::read(self.store.clip_file(id, FILE)).ok()?;
        match serde_json::from_slice(&bytes) {
            Ok(recovered) => Some(recovered),
            Err(e) => {
                tracing::warn!(clip = id, "unreadable {FILE}, ignored: {e}");
                None
            }
        }
    }

    /// The cameras the input camera of clip `record` follows: the given ones, else the
    /// recovered ones, else none (the identity).
    pub fn input_cameras(&self, record: &ClipRecord) -> Option<ClipCameras> {
        record
            .cameras
            .clone()
            .or_else(|| self.recovered_cameras(&record.id).map(|r| r.cameras))
    }

    /// [`input_cameras`](Self::input_cameras) when one of `specs` names the input camera, else
    /// `None` without looking: a stated camera needs none, and finding the recovered ones reads a
    /// file, which a render or trajectory of stated cameras should not pay for.
    pub fn input_cameras_for<'a>(
        &self,
        record: &ClipRecord,
        specs: impl IntoIterator<Item = &'a CameraSpec>,
    ) -> Option<ClipCameras> {
        specs
            .into_iter()
            .any(|spec| spec.input.is_some())
            .then(|| self.input_cameras(record))
            .flatten()
    }

    /// Context frame `k` of clip `id` as the model saw it: RGB in 0..1 at its input size.
    fn model_view(&self, id: &str, k: usize) -> Result<Vec<f32>, ServiceError> {
        let bytes = std::fs::read(self.store.frame_path(id, k))
            .map_err(|e| ServiceError::Internal(format!("cannot read context frame {k}: {e}")))?;
        self.seen_by_model(&decode_frame(&bytes)?)
    }

    /// A frame as the model sees it (centre-cropped and resized to its input): RGB in 0..1.
    pub(crate) fn seen_by_model(&self, frame: &RgbImage) -> Result<Vec<f32>, ServiceError> {
        let input = &self.engine.manifest().input;
        let frame = crop_and_resize(frame, input.width, input.height)?;
        Ok(frame
            .into_raw()
            .into_iter()
            .map(|v| f32::from(v) / 255.0)
            .collect())
    }

    fn align_frames(
        &self,
        record: &ClipRecord,
        sets: &[(f64, GaussianSet)],
        targets: &[Vec<f32>],
        options: RecoverOptions,
    ) -> Result<RecoveredCameras, ServiceError> {
        let input = &self.engine.manifest().input;
        let (w, h) = (input.width, input.height);
        let mut align = AlignOptions::default();
        align.render.footprint = self.renderer.footprint();
        let mut focal = NormalizedIntrinsics::C4G_DEFAULT;
        if options.refine_focal {
            let first_pass = AlignOptions {
                refine_focal: true,
                ..align.clone()
            };
            let fits = chain(sets, targets, focal, w, h, &first_pass, true)?;
            let mut scales: Vec<f32> = fits
                .iter()
                .map(|a| a.camera.intrinsics().fx / (focal.fx * w as f32))
                .filter(|s| s.is_finite() && *s > 0.0)
                .collect();
            scales.sort_by(f32::total_cmp);
            if let Some(&median) = scales.get(scales.len() / 2) {
                focal.fx *= median;
                focal.fy *= median;
            }
        }
        let fits = chain(sets, targets, focal, w, h, &align, false)?;
        let frames = fits
            .iter()
            .zip(&record.context_times)
            .map(|(a, &t)| ContextCamera {
                t,
                world_to_camera: row_major(a.camera.world_to_camera()),
                intrinsics: Intrinsics {
                    fx: f64::from(focal.fx),
                    fy: f64::from(focal.fy),
                    cx: f64::from(focal.cx),
                    cy: f64::from(focal.cy),
                },
            })
            .collect();
        let fits = fits
            .iter()
            .zip(&record.context_times)
            .map(|(a, &t)| FrameFit {
                t,
                initial_residual: a.initial_residual,
                residual: a.residual,
                confidence: a.confidence,
                coverage: a.coverage,
                conditioning: a.conditioning,
                iterations: a.iterations,
                converged: a.converged,
            })
            .collect();
        Ok(RecoveredCameras {
            cameras: ClipCameras {
                format: "recovered".to_owned(),
                scale: 1.0,
                frames,
                notes: vec![
                    "recovered by photometric alignment of the model's own Gaussians: poses in \
                     the model's units, the first context camera the identity"
                        .to_owned(),
                ],
                scale_fit: None,
            },
            fits,
            options,
        })
    }

    fn keep_recovered(&self, id: &str, recovered: &RecoveredCameras) -> Result<(), ServiceError> {
        let path = self.store.clip_file(id, FILE);
        let json = serde_json::to_vec_pretty(recovered)
            .map_err(|e| ServiceError::Internal(format!("cannot serialise {FILE}: {e}")))?;
        let tmp = path.with_extension(format!("tmp-{}", std::process::id()));
        let dir = path.parent().unwrap_or(Path::new("."));
        write_synced(&tmp, &json)
            .and_then(|()| std::fs::rename(&tmp, &path))
            .and_then(|()| sync_dir(dir))
            .map_err(|e| {
                let _ = std::fs::remove_file(&tmp);
                ServiceError::storage(
                    format!("cannot keep the recovered cameras of clip {id}"),
                    &e,
                )
            })
    }
}

/// Aligns every frame in order, each from the previous one's camera; the first frame's pose is
/// the identity (it is moved only when `free_first`, for its focal, and set back after).
fn chain(
    sets: &[(f64, GaussianSet)],
    targets: &[Vec<f32>],
    intrinsics: NormalizedIntrinsics,
    w: u32,
    h: u32,
    options: &AlignOptions,
    free_first: bool,
) -> Result<Vec<Alignment>, ServiceError> {
    let identity = Camera::from_normalized(intrinsics, w, h, Affine3A::IDENTITY)?;
    let mut previous = identity;
    let mut out = Vec::with_capacity(sets.len());
    for (k, ((_, set), target)) in sets.iter().zip(targets).enumerate() {
        let fit = if k == 0 && !free_first {
            // The model's frame is the first camera's: nothing to recover, only its residual.
            let one_step = AlignOptions {
                max_iterations: 1,
                ..options.clone()
            };
            let mut fit = c4g_analysis::align_camera(set, target, &identity, &one_step)?;
            fit.camera = identity;
            fit.residual = fit.initial_residual;
            fit.iterations = 0;
            fit.converged = true;
            fit
        } else {
            c4g_analysis::align_camera(set, target, &previous, options)?
        };
        previous = fit.camera;
        out.push(fit);
    }
    Ok(out)
}

/// A pose as the row-major 4×4 list a `ContextCamera` holds.
fn row_major(pose: Affine3A) -> Vec<f64> {
    Mat4::from(pose)
        .transpose()
        .to_cols_array()
        .iter()
        .map(|&v| f64::from(v))
        .collect()
}
