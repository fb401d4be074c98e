//! Clip intake: untrusted uploads in, timed context frames out.
//!
//! An upload is a video (read by FFmpeg in a child process, so that hostile media can at worst
//! crash that process), an image archive (zip or tar), or a list of image frames. Every limit is
//! checked on what the media declares before anything large is decoded, and again on what is
//! actually read. Then [`sampling`] picks the context frames.
//!
//! | module | holds |
//! |---|---|
//! | `sniff` | what kind of media some bytes are |
//! | `video` | FFmpeg / ffprobe as subprocesses with time limits |
//! | `images` | zip and tar archives, image frames, decompression limits |
//! | `sampling` | which frames become context frames |
//! | [`cameras`] | given cameras (a JSON list, COLMAP text, nerfstudio's `transforms.json`) |

pub mod cameras;
pub mod images;
mod sampling;
pub mod sniff;
mod video;

use std::path::PathBuf;

use bytes::Bytes;
use image::RgbImage;
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

use crate::ServiceError;
use crate::config::Limits;
pub use sniff::MediaKind;

/// What the client sent.
#[derive(Debug, Clone)]
pub enum Media {
    /// One file: a video or an image archive (sniffed from its bytes unless `kind` says).
    File {
        /// The bytes.
        data: Bytes,
        /// What the client says it is, if it says.
        kind: Option<MediaKind>,
    },
    /// Image frames, in order.
    Frames(Vec<Bytes>),
}

impl Media {
    /// Total bytes received.
    pub fn len(&self) -> usize {
        match self {
            Media::File { data, .. } => data.len(),
            Media::Frames(frames) => frames.iter().map(Bytes::len).sum(),
        }
    }

    /// True when nothing was sent.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    fn hash_into(&self, hasher: &mut Sha256) {
        match self {
            Media::File { data, .. } => {
                hasher.update(b"file\0");
                hasher.update(data);
            }
            Media::Frames(frames) => {
                for frame in frames {
                    hasher.update(b"frame\0");
                    hasher.update((frame.len() as u64).to_le_bytes());
                    hasher.update(frame);
                }
            }
        }
    }
}

/// How the client wants its clip read. Every field is optional.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct IntakeOptions {
    /// Frame rate of image frames without timestamps (default 10).
    pub fps: Option<f64>,
    /// Explicit times of image frames, seconds, strictly increasing.
    pub timestamps: Option<Vec<f64>>,
    /// At most this many context frames, spread evenly over the window.
    pub max_frames: Option<usize>,
    /// Every `stride`-th frame of the window instead.
    pub stride: Option<usize>,
    /// Window start, seconds.
    pub start: Option<f64>,
    /// Window end, seconds.
    pub end: Option<f64>,
    /// One camera per source frame, as the client sent them. Not serialised with the options:
    /// the clip stores them read ([`cameras::ClipCameras`]); [`clip_id`] hashes them.
    #[serde(skip)]
    pub cameras: Option<cameras::CameraInput>,
}

/// Frame rate given to image frames that have neither timestamps nor an fps.
pub const DEFAULT_IMAGE_FPS: f64 = 10.0;

/// What the source was, for the clip's description.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SourceInfo {
    /// `video` or `images`.
    pub kind: String,
    /// Frames in the source: for a video, the frames that decode (not what its container
    /// declares).
    pub frames: usize,
    /// Frame width, pixels.
    pub width: u32,
    /// Frame height, pixels.
    pub height: u32,
    /// Time of the last frame, seconds (the first is at 0).
    pub duration: f64,
    /// The rate of a video's frames (frames after the first over the time of the last; the
    /// container's average rate where it agrees within 1%), or the fps image frames were given.
    pub fps: f64,
    /// What the client should know about how the source was read, when it was not as the
    /// container declared: frames that did not decode and were skipped, a frame size that
    /// changes, a decode that ended early. Absent (empty) in clips stored before it was recorded.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub warnings: Vec<String>,
}

/// A context frame: its media time and its pixels.
#[derive(Debug, Clone)]
pub struct TimedFrame {
    /// Its index among the source's frames (which given camera is its).
    pub source_index: usize,
    /// Seconds from the source's first frame.
    pub time: f64,
    /// The frame at source resolution.
    pub image: RgbImage,
}

/// The context frames of an upload and what the source was.
#[derive(Debug, Clone)]
pub struct Intake {
    /// Chosen context frames, in time order.
    pub frames: Vec<TimedFrame>,
    /// The source.
    pub source: SourceInfo,
    /// Seconds between source frames ([`frame_step`]), when known: the time policy's floor.
    pub frame_step: Option<f64>,
}

/// The source's frame step: the median of the positive gaps between consecutive frame times when
/// there are any, else the frame period `1 / fps`, else unknown.
///
/// The median, not the smallest gap: C4G was trained on integer frame indices, so "one source
/// frame" is what the time policy's floor stands for, and real files (variable frame rate, a
/// near-duplicate timestamp, a dropped frame) have outlying gaps that must not set it. A tiny
/// floor would let the normalised times grow as large as span / step.
pub fn frame_step(times: &[f64], fps: f64) -> Option<f64> {
    let positive = |s: &f64| s.is_finite() && *s > 0.0;
    let mut gaps: Vec<f64> = times
        .windows(2)
        .map(|w| w[1] - w[0])
        .filter(positive)
        .collect();
    gaps.sort_by(f64::total_cmp);
    gaps.get(gaps.len() / 2)
        .copied()
        .or_else(|| Some(1.0 / fps).filter(positive))
}

/// Where intake finds its tools and puts its temporary files.
#[derive(Debug, Clone)]
pub struct IntakeTools {
    /// The FFmpeg binary.
    pub ffmpeg: PathBuf,
    /// The ffprobe binary.
    pub ffprobe: PathBuf,
    /// Scratch space for videos (FFmpeg needs a seekable file for most containers).
    pub scratch: PathBuf,
}

impl IntakeTools {
    /// Tools from an FFmpeg path: ffprobe beside it when it is a path, else on PATH.
    pub fn new(ffmpeg: PathBuf, scratch: PathBuf) -> Self {
        let ffprobe = match ffmpeg.parent() {
            Some(dir) if !dir.as_os_str().is_empty() => dir.join("ffprobe"),
            _ => PathBuf::from("ffprobe"),
        };
        Self {
            ffmpeg,
            ffprobe,
            scratch,
        }
    }
}

/// The content address of an upload: the same media read with the same options for the same
/// model gives the same id.
pub fn clip_id(model_identity: &str, media: &Media, options: &IntakeOptions) -> String {
    let mut hasher = Sha256::new();
    hasher.update(model_identity.as_bytes());
    hasher.update(b"\0");
    // Serialising a struct of options is deterministic (fields in declaration order).
    hasher.update(serde_json::to_vec(options).unwrap_or_default());
    hasher.update(b"\0");
    // Absent cameras add nothing, so clips uploaded before cameras existed keep their ids.
    if let Some(cameras) = &options.cameras {
        cameras.hash_into(&mut hasher);
    }
    media.hash_into(&mut hasher);
    hex::encode(&hasher.finalize()[..12])
}

/// Reads an upload into context frames, holding it to `limits`.
pub async fn read(
    media: Media,
    options: &IntakeOptions,
    limits: &Limits,
    tools: &IntakeTools,
) -> Result<Intake, ServiceError> {
    validate_options(options, limits)?;
    if media.is_empty() {
        return Err(ServiceError::invalid(
            "the upload is empty: send a video file, an image archive (zip, tar) or image frames",
        ));
    }
    let kind = match &media {
        Media::Frames(_) => MediaKind::Frames,
        Media::File { data, kind } => match kind {
            Some(kind) => *kind,
            None => sniff::sniff(data),
        },
    };
    match (kind, media) {
        (MediaKind::Video | MediaKind::Unknown, Media::File { data, .. }) => {
            video::read(data, kind, options, limits, tools).await
        }
        (kind, media) => {
            let (options, limits) = (options.clone(), limits.clone());
            tokio::task::spawn_blocking(move || images::read(media, kind, &options, &limits))
                .await
                .map_err(|e| ServiceError::Internal(format!("image intake panicked: {e}")))?
        }
    }
}

/// Checks an upload's options against the limits before any media is read (the fuzz targets
/// call it on their own).
pub fn validate_options(options: &IntakeOptions, limits: &Limits) -> Result<(), ServiceError> {
    for (name, value) in [
        ("fps", options.fps),
        ("start", options.start),
        ("end", options.end),
    ] {
        if let Some(v) = value
            && !v.is_finite()
        {
            return Err(ServiceError::invalid(format!(
                "{name} must be a finite number, got {v}"
            )));
        }
    }
    if let Some(fps) = options.fps
        && fps <= 0.0
    {
        return Err(ServiceError::invalid(format!(
            "fps must be positive, got {fps}"
        )));
    }
    if let (Some(start), Some(end)) = (options.start, options.end)
        && start > end
    {
        return Err(ServiceError::invalid(format!(
            "the window start {start} is after its end {end}"
        )));
    }
    if let Some(n) = options.max_frames
        && (n == 0 || n > limits.max_context_frames)
    {
        return Err(ServiceError::invalid(format!(
            "max_frames must be between 1 and {} (C4G_MAX_CONTEXT_FRAMES), got {n}",
            limits.max_context_frames
        )));
    }
    if let Some(stride) = options.stride
        && (stride == 0 || stride > limits.max_source_frames)
    {
        return Err(ServiceError::invalid(format!(
            "stride must be between 1 and {} (C4G_MAX_SOURCE_FRAMES), got {stride}",
            limits.max_source_frames
        )));
    }
    if let Some(times) = &options.timestamps {
        if let Some(t) = times.iter().find(|t| !t.is_finite()) {
            return Err(ServiceError::invalid(format!(
                "timestamps must be finite, got {t}"
            )));
        }
        if times.windows(2).any(|w| w[0] >= w[1]) {
            return Err(ServiceError::invalid(
                "timestamps must be strictly increasing",
            ));
        }
    }
    Ok(())
}

/// Frame-size checks shared by videos and images.
fn check_frame_size(width: u32, height: u32, limits: &Limits) -> Result<(), ServiceError> {
    if width > limits.max_side || height > limits.max_side {
        return Err(ServiceError::TooLarge(format!(
            "frames are {width}x{height}; the largest side allowed is {} pixels (C4G_MAX_SIDE)",
            limits.max_side
        )));
    }
    if width < limits.min_side || height < limits.min_side {
        return Err(ServiceError::UnreadableMedia(format!(
            "frames are {width}x{height}; both sides must be at least {} pixels (C4G_MIN_SIDE)",
            limits.min_side
        )));
    }
    Ok(())
}

fn check_frame_count(frames: usize, limits: &Limits) -> Result<(), ServiceError> {
    if frames > limits.max_source_frames {
        return Err(ServiceError::TooLarge(format!(
            "the clip has {frames} frames; at most {} are accepted (C4G_MAX_SOURCE_FRAMES)",
            limits.max_source_frames
        )));
    }
    Ok(())
}

fn check_duration(duration: f64, limits: &Limits) -> Result<(), ServiceError> {
    if duration > limits.max_duration_s {
        return Err(ServiceError::TooLarge(format!(
            "the clip lasts {duration:.1} s; at most {} s are accepted (C4G_MAX_DURATION_S)",
            limits.max_duration_s
        )));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_frame_step_is_the_median_gap_between_source_frames_else_the_frame_period() {
        let at_30fps: Vec<f64> = (0..10).map(|i| f64::from(i) / 30.0).collect();
        let step = frame_step(&at_30fps, 25.0).unwrap();
        assert!((step - 1.0 / 30.0).abs() < 1e-12, "{step}");
        // A near-duplicate timestamp and a dropped frame do not set the step.
        let step = frame_step(&[0.0, 0.1, 0.100_001, 0.2, 0.3, 0.5], 10.0).unwrap();
        assert!((step - 0.1).abs() < 1e-9, "{step}");
        // One frame: the declared rate; no rate either: unknown.
        assert_eq!(frame_step(&[0.0], 10.0), Some(0.1));
        assert_eq!(frame_step(&[0.0], 0.0), None);
        assert_eq!(frame_step(&[], f64::NAN), None);
    }

    #[test]
    fn a_source_stored_before_warnings_were_recorded_loads_and_an_empty_list_is_not_written() {
        let old: SourceInfo = serde_json::from_value(serde_json::json!({
            "kind": "video", "frames": 141, "width": 368, "height": 480, "duration": 7.0, "fps": 20.0,
        }))
        .unwrap();
        assert!(old.warnings.is_empty());
        assert!(
            serde_json::to_value(&old)
                .unwrap()
                .get("warnings")
                .is_none()
        );
        let warned = SourceInfo {
            warnings: vec!["skipped".into()],
            ..old
        };
        assert_eq!(
            serde_json::to_value(&warned).unwrap()["warnings"][0],
            "skipped"
        );
    }
}
