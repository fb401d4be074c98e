//! What an upload is and what the intake makes of it: the media, how to read it, what the
//! source was, the timed frames, the tools, and the clip id that content-addresses it.

use std::path::PathBuf;

use bytes::Bytes;
use image::RgbImage;
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

use crate::clips::intake::sniff::MediaKind;

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
    pub cameras: Option<crate::clips::intake::cameras::CameraInput>,
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
    /// Source frames kept for fits, shrunk, in time order ([`super::kept`]).
    pub kept: Vec<TimedFrame>,
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

    /// Empties scratch space, and says how many entries went. Called when the service starts:
    /// no request of this process owns anything there yet, and what a killed process was
    /// reading (a whole upload each) would otherwise stay for good.
    pub fn clear_scratch(&self) -> usize {
        let Ok(entries) = std::fs::read_dir(&self.scratch) else {
            return 0;
        };
        entries
            .flatten()
            .filter(|entry| {
                let path = entry.path();
                std::fs::remove_file(&path)
                    .or_else(|_| std::fs::remove_dir_all(&path))
                    .is_ok()
            })
            .count()
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
