//! Rendering requests: cameras as clients state them, the rasterizer choice, and image and video
//! encoding.

use std::io::Cursor;
use std::path::Path;
use std::process::Stdio;

use c4g_renderer::{
    Camera, CpuRasterizer, GaussianSet, Image, NormalizedIntrinsics, Rasterizer, RenderOptions,
};
use glam::{Affine3A, Mat4};
use serde::{Deserialize, Serialize};
use tokio::io::AsyncWriteExt;
use tokio::process::Command;

use crate::ApiError;
use crate::config::RendererArg;

/// A camera as a client states it: a row-major 4×4 world-to-camera matrix (OpenCV axes) and
/// intrinsics as fractions of the image size. Both default to the first context camera's.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CameraSpec {
    /// 16 numbers, row-major, last row 0 0 0 1.
    pub world_to_camera: Option<Vec<f32>>,
    /// Normalised intrinsics.
    pub intrinsics: Option<IntrinsicsSpec>,
}

/// Intrinsics as fractions of the image size.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct IntrinsicsSpec {
    /// Focal length over width.
    pub fx: f32,
    /// Focal length over height.
    pub fy: f32,
    /// Principal point x over width.
    #[serde(default = "half")]
    pub cx: f32,
    /// Principal point y over height.
    #[serde(default = "half")]
    pub cy: f32,
}

fn half() -> f32 {
    0.5
}

impl CameraSpec {
    /// The camera at `width` × `height`.
    pub fn camera(&self, width: u32, height: u32) -> Result<Camera, ApiError> {
        let pose = match &self.world_to_camera {
            None => Affine3A::IDENTITY,
            Some(m) if m.len() == 16 => {
                let rows = Mat4::from_cols_slice(m).transpose();
                if rows.row(3) != glam::Vec4::W {
                    return Err(ApiError::invalid(format!(
                        "world_to_camera must end in the row 0 0 0 1, got {:?}",
                        &m[12..]
                    )));
                }
                Affine3A::from_mat4(rows)
            }
            Some(m) => {
                return Err(ApiError::invalid(format!(
                    "world_to_camera needs 16 numbers (row-major 4x4), got {}",
                    m.len()
                )));
            }
        };
        let intrinsics = self
            .intrinsics
            .map(|i| NormalizedIntrinsics {
                fx: i.fx,
                fy: i.fy,
                cx: i.cx,
                cy: i.cy,
            })
            .unwrap_or(NormalizedIntrinsics::C4G_DEFAULT);
        Ok(Camera::from_normalized(intrinsics, width, height, pose)?)
    }
}

/// What a render answers with.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ImageFormat {
    /// 8-bit RGB PNG.
    #[default]
    Png,
    /// Raw little-endian f32 expected depth.
    Depth,
    /// Raw little-endian f32 accumulated opacity.
    Alpha,
    /// H.264 in MP4 (trajectories).
    Mp4,
}

impl ImageFormat {
    /// The HTTP content type.
    pub fn content_type(self) -> &'static str {
        match self {
            ImageFormat::Png => "image/png",
            ImageFormat::Depth | ImageFormat::Alpha => "application/octet-stream",
            ImageFormat::Mp4 => "video/mp4",
        }
    }
}

/// The rasterizer the service renders with.
pub struct Renderer {
    inner: Box<dyn Rasterizer + Send + Sync>,
    name: String,
}

impl Renderer {
    /// The rasterizer `choice` asks for. `auto` takes wgpu only on a hardware GPU: on a CPU,
    /// the CPU rasterizer is faster than wgpu on Mesa's software Vulkan.
    pub fn new(choice: RendererArg) -> Result<Self, String> {
        #[cfg(feature = "gpu")]
        {
            use c4g_renderer::GpuRasterizer;
            match (choice, GpuRasterizer::new()) {
                (RendererArg::Gpu, Ok(gpu)) => return Ok(Self::gpu(gpu)),
                (RendererArg::Gpu, Err(e)) => return Err(format!("no wgpu adapter: {e}")),
                (RendererArg::Auto, Ok(gpu)) if !gpu.adapter().software => {
                    return Ok(Self::gpu(gpu));
                }
                _ => {}
            }
        }
        #[cfg(not(feature = "gpu"))]
        if choice == RendererArg::Gpu {
            return Err("`--renderer gpu` needs c4g-server built with `--features gpu`".into());
        }
        Ok(Self {
            inner: Box::new(CpuRasterizer::new()),
            name: "cpu".into(),
        })
    }

    #[cfg(feature = "gpu")]
    fn gpu(gpu: c4g_renderer::GpuRasterizer) -> Self {
        let name = format!("wgpu ({})", gpu.adapter().name);
        Self {
            inner: Box::new(gpu),
            name,
        }
    }

    /// Which rasterizer this is, for `/v1/models` and logs.
    pub fn name(&self) -> &str {
        &self.name
    }

    /// Renders one view.
    pub fn render(
        &self,
        set: &GaussianSet,
        camera: &Camera,
        background: [f32; 3],
    ) -> Result<Image, ApiError> {
        let options = RenderOptions {
            background,
            features: false,
            ..RenderOptions::default()
        };
        Ok(self.inner.render(set, camera, &options)?)
    }
}

/// One image in `format` (not MP4).
pub fn encode_image(image: &Image, format: ImageFormat) -> Result<Vec<u8>, ApiError> {
    match format {
        ImageFormat::Png => {
            let rgb = to_rgb8(image);
            let mut bytes = Vec::new();
            image::write_buffer_with_format(
                &mut Cursor::new(&mut bytes),
                &rgb,
                image.width,
                image.height,
                image::ExtendedColorType::Rgb8,
                image::ImageFormat::Png,
            )
            .map_err(|e| ApiError::Internal(format!("PNG encoding failed: {e}")))?;
            Ok(bytes)
        }
        ImageFormat::Depth => Ok(le_bytes(&image.expected_depth)),
        ImageFormat::Alpha => Ok(le_bytes(&image.alpha)),
        ImageFormat::Mp4 => Err(ApiError::invalid(
            "mp4 is for trajectories: add a \"trajectory\" (or use png, depth or alpha)",
        )),
    }
}

/// 8-bit RGB, rounding and clamping each channel.
pub fn to_rgb8(image: &Image) -> Vec<u8> {
    image
        .rgb
        .iter()
        .map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8)
        .collect()
}

/// Floats as packed little-endian bytes (raw depth and alpha, prompt embeddings on the wire).
pub(crate) fn le_bytes(values: &[f32]) -> Vec<u8> {
    values.iter().flat_map(|v| v.to_le_bytes()).collect()
}

/// Frames (RGB8, all `width` × `height`) as an H.264 MP4 at `fps`, by FFmpeg. Odd sizes are padded
/// by one pixel (H.264 in 4:2:0 needs even sides).
pub async fn encode_mp4(
    ffmpeg: &Path,
    scratch: &Path,
    frames: &[Vec<u8>],
    width: u32,
    height: u32,
    fps: f64,
) -> Result<Vec<u8>, ApiError> {
    std::fs::create_dir_all(scratch)
        .map_err(|e| ApiError::Internal(format!("cannot create the scratch directory: {e}")))?;
    let out = tempfile::Builder::new()
        .suffix(".mp4")
        .tempfile_in(scratch)
        .map_err(|e| ApiError::Internal(format!("cannot create a scratch file: {e}")))?;
    let mut child = Command::new(ffmpeg)
        .args([
            "-v", "error", "-y", "-f", "rawvideo", "-pix_fmt", "rgb24", "-s",
        ])
        .arg(format!("{width}x{height}"))
        .arg("-r")
        .arg(format!("{fps}"))
        .args(["-i", "pipe:0", "-vf", "pad=ceil(iw/2)*2:ceil(ih/2)*2"])
        .args(["-c:v", "libx264", "-pix_fmt", "yuv420p", "-crf", "18"])
        .args(["-movflags", "+faststart", "-f", "mp4"])
        .arg(out.path())
        .stdin(Stdio::piped())
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .kill_on_drop(true)
        .spawn()
        .map_err(|e| {
            ApiError::Internal(format!(
                "cannot run {}: {e} (install FFmpeg, or point C4G_FFMPEG at it)",
                ffmpeg.display()
            ))
        })?;
    if let Some(mut stdin) = child.stdin.take() {
        for frame in frames {
            stdin
                .write_all(frame)
                .await
                .map_err(|e| ApiError::Internal(format!("feeding ffmpeg: {e}")))?;
        }
    }
    let output = child
        .wait_with_output()
        .await
        .map_err(|e| ApiError::Internal(format!("waiting for ffmpeg: {e}")))?;
    if !output.status.success() {
        return Err(ApiError::Internal(format!(
            "ffmpeg could not encode the video: {}",
            String::from_utf8_lossy(&output.stderr).trim()
        )));
    }
    tokio::fs::read(out.path())
        .await
        .map_err(|e| ApiError::Internal(format!("reading the encoded video: {e}")))
}
