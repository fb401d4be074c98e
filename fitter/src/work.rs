//! One fit job's work: the job's message in, the fitted scene and what the fit did out.
//!
//! The server sends frames as it keeps them (small PNGs) with each frame's input camera in the
//! model's frame: a world-to-camera pose and intrinsics as fractions of the model's square centre
//! crop. Here the frames are brought to the job's working resolution (never enlarged) and the
//! intrinsics mapped onto the whole frame (the crop is the centred square of side `min(W, H)`:
//! `fx_px = fx · side`, `cx_px = cx · side + (W − side) / 2`, and likewise in y), so a fit covers
//! the whole frame at its aspect ratio. The feed-forward start covers only the crop, so the rest
//! is covered first (`c4g_fit::cover_frame`), unless the job asks for no steps: then the start is
//! the answer, unchanged.

use c4g_fit::{Control, FitSettings, FittedScene, Frame, Progress, fit, working_size};
use c4g_proto::v1 as pb;
use c4g_scene::{Camera, Intrinsics};
use glam::Mat4;
use image::imageops::FilterType;
use serde::Deserialize;

/// What went wrong with a job, and whether another attempt could help.
#[derive(Debug)]
pub struct WorkError {
    /// What, in words.
    pub message: String,
    /// False for bad input (the job fails for good).
    pub retryable: bool,
}

fn bad(message: impl Into<String>) -> WorkError {
    WorkError {
        message: message.into(),
        retryable: false,
    }
}

/// The settings as the server sends them.
#[derive(Debug, Deserialize)]
struct Settings {
    steps: u64,
    resolution: u32,
    max_gaussians: usize,
    keyframe_every: usize,
    holdout_every: usize,
    refine_cameras: bool,
    time_budget_s: Option<f64>,
    seed: u64,
    max_frames: usize,
}

/// A job ready to fit.
pub struct Prepared {
    /// The settings.
    pub settings: FitSettings,
    /// The frames at the working size.
    pub frames: Vec<Frame>,
    /// The start (covered outside the crop when the job takes steps).
    pub start: FittedScene,
    /// Working size.
    pub size: (u32, u32),
}

/// Reads a job's message.
pub fn prepare(job: &pb::FitJob) -> Result<Prepared, WorkError> {
    let s: Settings = serde_json::from_str(&job.settings_json)
        .map_err(|e| bad(format!("unreadable settings: {e}")))?;
    let settings = FitSettings {
        steps: s.steps,
        resolution: s.resolution,
        max_gaussians: s.max_gaussians,
        keyframe_every: s.keyframe_every,
        holdout_every: s.holdout_every,
        refine_cameras: s.refine_cameras,
        time_budget_s: s.time_budget_s,
        seed: s.seed,
        max_frames: s.max_frames,
    };
    settings.check().map_err(|e| bad(e.to_string()))?;
    if job.frames.is_empty() {
        return Err(bad("a fit needs at least one frame"));
    }
    let mut start =
        c4g_fit::file::from_bytes(&job.start).map_err(|e| bad(format!("unreadable start: {e}")))?;
    let mut frames = Vec::with_capacity(job.frames.len());
    let mut size = (0, 0);
    for (k, f) in job.frames.iter().enumerate() {
        let image = image::load_from_memory(&f.png)
            .map_err(|e| bad(format!("frame {k} is not an image: {e}")))?
            .to_rgb8();
        let (w, h) = working_size(image.width(), image.height(), settings.resolution);
        let image = if (image.width(), image.height()) == (w, h) {
            image
        } else {
            image::imageops::resize(&image, w, h, FilterType::Triangle)
        };
        size = (w, h);
        frames.push(Frame {
            time: f.time,
            rgb: image
                .as_raw()
                .iter()
                .map(|&v| f32::from(v) / 255.0)
                .collect(),
            camera: camera(f, w, h).map_err(|e| bad(format!("frame {k}'s camera: {e}")))?,
        });
    }
    if settings.steps > 0 {
        let spacing = (size.0.max(size.1) / 64).max(2);
        let added = c4g_fit::cover_frame(&mut start, &frames[0], spacing);
        tracing::info!(added, "Gaussians added outside the model's crop");
    }
    Ok(Prepared {
        settings,
        frames,
        start,
        size,
    })
}

/// The frame's camera at `w` × `h` (the module documentation maps the crop's intrinsics).
fn camera(f: &pb::FitFrame, w: u32, h: u32) -> Result<Camera, String> {
    let pose: [f64; 16] = f
        .world_to_camera
        .as_slice()
        .try_into()
        .map_err(|_| format!("{} pose values, not 16", f.world_to_camera.len()))?;
    if pose
        .iter()
        .chain([&f.fx, &f.fy, &f.cx, &f.cy])
        .any(|v| !v.is_finite())
    {
        return Err("non-finite values".into());
    }
    let side = f64::from(w.min(h));
    let intrinsics = Intrinsics {
        fx: (f.fx * side) as f32,
        fy: (f.fy * side) as f32,
        cx: (f.cx * side + (f64::from(w) - side) / 2.0) as f32,
        cy: (f.cy * side + (f64::from(h) - side) / 2.0) as f32,
        width: w,
        height: h,
    };
    let row_major: [f32; 16] = pose.map(|v| v as f32);
    let matrix = Mat4::from_cols_array(&row_major).transpose();
    Camera::from_world_to_camera_matrix(intrinsics, matrix).map_err(|e| e.to_string())
}

/// The scene's size for the learning rates: the median distance of the start's Gaussians from
/// the first camera's centre (1 for an empty start).
fn extent(start: &FittedScene, camera: &Camera) -> f64 {
    let Some(set) = start.sets.first() else {
        return 1.0;
    };
    let centre = camera.position();
    let mut d: Vec<f64> = set
        .positions()
        .iter()
        .map(|m| f64::from(glam::Vec3::from(*m).distance(centre)))
        .filter(|d| d.is_finite())
        .collect();
    if d.is_empty() {
        return 1.0;
    }
    d.sort_by(f64::total_cmp);
    d[d.len() / 2].max(1e-3)
}

/// What the fit did, as the server reads it (`outcome_json`).
#[derive(Debug, serde::Serialize)]
pub struct Outcome {
    steps: u64,
    seconds: f64,
    holdout_frames: Vec<usize>,
    holdout_psnr_before: Option<f64>,
    holdout_psnr_after: Option<f64>,
    train_psnr: f64,
    stopped: bool,
    resolution: [u32; 2],
    still_share: Option<f64>,
}

/// Fits `prepared`; `progress` sees every step and may stop it. The fitted scene's bytes and the
/// outcome.
pub fn run(
    prepared: &Prepared,
    progress: impl FnMut(&Progress) -> Control,
) -> Result<(Vec<u8>, Outcome), WorkError> {
    let extent = extent(&prepared.start, &prepared.frames[0].camera);
    let options = prepared.settings.options(extent);
    let (scene, report) =
        fit(&prepared.start, &prepared.frames, &options, progress).map_err(|e| WorkError {
            message: e.to_string(),
            retryable: false,
        })?;
    let outcome = Outcome {
        steps: report.steps,
        seconds: report.seconds,
        holdout_frames: report.holdout_frames,
        holdout_psnr_before: report.holdout_psnr_before,
        holdout_psnr_after: report.holdout_psnr_after,
        train_psnr: report.train_psnr_after,
        stopped: report.stopped,
        resolution: [prepared.size.0, prepared.size.1],
        still_share: report.still_share,
    };
    Ok((c4g_fit::file::to_bytes(&scene), outcome))
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    fn frame(w: u32, h: u32) -> pb::FitFrame {
        let mut png = Vec::new();
        image::RgbImage::new(w, h)
            .write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
            .unwrap();
        pb::FitFrame {
            time: 0.0,
            png,
            world_to_camera: vec![
                1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0,
            ],
            fx: 0.8,
            fy: 0.8,
            cx: 0.5,
            cy: 0.5,
        }
    }

    /// The crop's intrinsics land on the whole frame: the principal point at the frame's centre,
    /// the focal length the crop's side times its fraction.
    #[test]
    fn crop_intrinsics_map_onto_the_whole_frame() {
        let c = camera(&frame(8, 4), 160, 90).unwrap();
        let i = c.intrinsics();
        assert_eq!((i.width, i.height), (160, 90));
        assert!((i.fx - 72.0).abs() < 1e-4 && (i.cx - 80.0).abs() < 1e-4);
        assert!((i.cy - 45.0).abs() < 1e-4);
        let mut broken = frame(8, 4);
        broken.world_to_camera.pop();
        assert!(camera(&broken, 16, 9).is_err());
    }
}
