//! What renders answer with: PNG, raw little-endian f32 depth and alpha, and H.264 MP4 (by
//! FFmpeg) for trajectories.

use std::io::Cursor;
use std::path::Path;
use std::process::Stdio;

use c4g_renderer::Image;
use serde::{Deserialize, Serialize};
use tokio::io::AsyncWriteExt;
use tokio::process::Command;

use crate::ServiceError;

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
    /// Raw little-endian f32 lifted features, `[H, W, F]` (`crate::views::features`).
    Features,
    /// The lifted features coloured by the clip's PCA basis, as an 8-bit RGB PNG.
    FeaturesPca,
}

impl ImageFormat {
    /// The HTTP content type.
    pub fn content_type(self) -> &'static str {
        match self {
            ImageFormat::Png | ImageFormat::FeaturesPca => "image/png",
            ImageFormat::Depth | ImageFormat::Alpha | ImageFormat::Features => {
                "application/octet-stream"
            }
            ImageFormat::Mp4 => "video/mp4",
        }
    }
}

/// One image in `format` (not MP4).
pub fn encode_image(image: &Image, format: ImageFormat) -> Result<Vec<u8>, ServiceError> {
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
            .map_err(|e| ServiceError::Internal(format!("PNG encoding failed: {e}")))?;
            Ok(bytes)
        }
        ImageFormat::Depth => Ok(le_bytes(&image.expected_depth)),
        ImageFormat::Alpha => Ok(le_bytes(&image.alpha)),
        ImageFormat::Mp4 => Err(ServiceError::invalid(
            "mp4 is for trajectories: add a \"trajectory\" (or use png, depth or alpha)",
        )),
        // Feature images are single views, made by `crate::views::features`.
        ImageFormat::Features | ImageFormat::FeaturesPca => Err(ServiceError::invalid(
            "feature images (features, features_pca) are single views: ask for one time and \
             camera, without a trajectory",
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
) -> Result<Vec<u8>, ServiceError> {
    std::fs::create_dir_all(scratch)
        .map_err(|e| ServiceError::storage("cannot create the scratch directory", &e))?;
    let out = tempfile::Builder::new()
        .suffix(".mp4")
        .tempfile_in(scratch)
        .map_err(|e| ServiceError::storage("cannot create a scratch file for the video", &e))?;
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
            ServiceError::Internal(format!(
                "cannot run {}: {e} (install FFmpeg, or point C4G_FFMPEG at it)",
                ffmpeg.display()
            ))
        })?;
    // A write that fails (FFmpeg gone: a full disk stops it mid-video) is judged by what FFmpeg
    // said, once it has ended, not by the broken pipe it leaves.
    let mut fed = Ok(());
    if let Some(mut stdin) = child.stdin.take() {
        for frame in frames {
            if let Err(e) = stdin.write_all(frame).await {
                fed = Err(e);
                break;
            }
        }
    }
    let output = child
        .wait_with_output()
        .await
        .map_err(|e| ServiceError::Internal(format!("waiting for ffmpeg: {e}")))?;
    if !output.status.success() || fed.is_err() {
        let log = String::from_utf8_lossy(&output.stderr);
        // FFmpeg says ENOSPC in words only: a full scratch disk is the client's 507, not a 500.
        if log.contains("No space left on device") {
            let full = std::io::Error::from(std::io::ErrorKind::StorageFull);
            return Err(ServiceError::storage("cannot write the video", &full));
        }
        let fed = fed.err().map(|e| format!("feeding it failed ({e}); "));
        return Err(ServiceError::Internal(format!(
            "ffmpeg could not encode the video: {}{}",
            fed.unwrap_or_default(),
            log.trim()
        )));
    }
    tokio::fs::read(out.path())
        .await
        .map_err(|e| ServiceError::Internal(format!("reading the encoded video: {e}")))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A stand-in for FFmpeg on a full disk (the real one cannot be made to fill a disk here
    /// without filling this machine's): it reads a little of the video, says what FFmpeg says on
    /// ENOSPC, and exits, so the service's later writes meet a closed pipe.
    fn ffmpeg_on_a_full_disk(dir: &Path) -> std::path::PathBuf {
        use std::os::unix::fs::PermissionsExt;
        let path = dir.join("ffmpeg");
        std::fs::write(
            &path,
            "#!/bin/sh\nhead -c 16 >/dev/null\necho 'out.mp4: No space left on device' >&2\nexit 1\n",
        )
        .unwrap();
        std::fs::set_permissions(&path, std::fs::Permissions::from_mode(0o755)).unwrap();
        path
    }

    #[tokio::test]
    async fn a_video_that_meets_a_full_disk_is_insufficient_storage_even_mid_feed() {
        let dir = tempfile::tempdir().unwrap();
        let ffmpeg = ffmpeg_on_a_full_disk(dir.path());
        // Far more than a pipe buffers: the feed is still going when the stand-in exits.
        let frames = vec![vec![0u8; 512 * 512 * 3]; 8];
        let e = encode_mp4(
            &ffmpeg,
            &dir.path().join("scratch"),
            &frames,
            512,
            512,
            10.0,
        )
        .await
        .unwrap_err();
        assert_eq!(
            e.kind(),
            crate::ServiceErrorKind::InsufficientStorage,
            "{e}"
        );
    }
}
