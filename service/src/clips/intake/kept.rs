//! Source frames kept for fits: a fit supervises a clip's scene with its own frames, many more
//! than the context frames the model encodes. They are read at upload, from the same media by the
//! same intake (so they keep the context frames' clock and window), spread evenly over the
//! window, and kept small: at most `count` of them, at most `side` pixels on the long side.
//!
//! Reading them is a second pass over the upload: FFmpeg decodes the video again (or the archive
//! is read again) for those frames. The frames of that pass are held at source size until they
//! are shrunk, so their count is also bounded by [`HELD_BYTES`]. On disk they cost about
//! `count` small PNGs a clip (48 frames at 256×144 are about 2-4 MB).

use image::RgbImage;
use image::imageops::FilterType;

use crate::ServiceError;
use crate::clips::intake::{IntakeOptions, IntakeTools, Media, SourceInfo, read};
use crate::config::Limits;

/// Most bytes of source-size frames the pass holds at once.
pub const HELD_BYTES: u64 = 256 << 20;

/// Up to `count` source frames of `media` (read as `options` say, whose first pass found
/// `source`), shrunk to at most `side` pixels on their long side, with their times.
pub async fn read_kept(
    media: Media,
    options: &IntakeOptions,
    limits: &Limits,
    tools: &IntakeTools,
    source: &SourceInfo,
    count: usize,
    side: u32,
) -> Result<(Vec<f64>, Vec<RgbImage>), ServiceError> {
    let frame_bytes = u64::from(source.width) * u64::from(source.height) * 3;
    let count = count.min(usize::try_from(HELD_BYTES / frame_bytes.max(1)).unwrap_or(usize::MAX));
    if count == 0 || side == 0 {
        return Ok((Vec::new(), Vec::new()));
    }
    let options = IntakeOptions {
        max_frames: Some(count),
        stride: None,
        cameras: None,
        ..options.clone()
    };
    let limits = Limits {
        max_context_frames: limits.max_context_frames.max(count),
        ..limits.clone()
    };
    let intake = read(media, &options, &limits, tools).await?;
    let (w, h) = small_size(source.width, source.height, side);
    tokio::task::spawn_blocking(move || {
        intake
            .frames
            .into_iter()
            .map(|f| {
                let image = if (f.image.width(), f.image.height()) == (w, h) {
                    f.image
                } else {
                    image::imageops::resize(&f.image, w, h, FilterType::Triangle)
                };
                (f.time, image)
            })
            .unzip()
    })
    .await
    .map_err(|e| ServiceError::Internal(format!("shrinking kept frames panicked: {e}")))
}

/// `width` × `height` shrunk (never enlarged) to at most `side` on the long side, aspect kept.
pub fn small_size(width: u32, height: u32, side: u32) -> (u32, u32) {
    let long = width.max(height).max(1);
    if long <= side {
        return (width.max(1), height.max(1));
    }
    let scale = f64::from(side) / f64::from(long);
    let shrink = |v: u32| ((f64::from(v) * scale).round() as u32).max(1);
    (shrink(width), shrink(height))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frames_shrink_to_the_long_side_keeping_the_aspect_and_never_grow() {
        assert_eq!(small_size(1920, 1080, 256), (256, 144));
        assert_eq!(small_size(1080, 1920, 256), (144, 256));
        assert_eq!(small_size(100, 50, 256), (100, 50));
        assert_eq!(small_size(5000, 1, 256), (256, 1));
    }
}
