//! What is known of a clip without its features: the record stored as `clip.json` beside them,
//! read by every layer above the store (and by other replicas through the shared store).

use std::time::{SystemTime, UNIX_EPOCH};

use serde::{Deserialize, Serialize};

use crate::clips::intake::cameras::ClipCameras;
use crate::clips::intake::{IntakeOptions, SourceInfo};

/// What the store knows about a clip without its features.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ClipRecord {
    /// Content address.
    pub id: String,
    /// The model's name.
    pub model: String,
    /// Seconds since the Unix epoch when it was encoded.
    pub created_at: u64,
    /// How the upload was read.
    pub options: IntakeOptions,
    /// What the upload was.
    pub source: SourceInfo,
    /// Context times in encoded (increasing) order.
    pub context_times: Vec<f64>,
    /// Where each encoded frame was in the caller's list.
    pub frame_order: Vec<usize>,
    /// `[T, P, C]` of the features.
    pub feature_shape: [usize; 3],
    /// Seconds between the source's frames, when known (the time policy's floor; see
    /// [`frame_step`](Self::frame_step)). Absent in clips stored before it was recorded.
    #[serde(default)]
    pub frame_step: Option<f64>,
    /// The context frames' given cameras in the model's frame, when the upload carried cameras.
    /// Absent in clips uploaded without them (and in clips stored before they were recorded).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cameras: Option<ClipCameras>,
    /// Source frames kept, small, for fits to supervise with (`source/NNN.png` beside the
    /// record). Absent in clips stored before they were kept, or with `C4G_KEPT_FRAMES=0`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub kept_frames: Option<KeptFrames>,
}

/// The source frames kept with a clip: up to `C4G_KEPT_FRAMES` of the window's frames spread
/// evenly (every frame of a shorter clip), at most `C4G_KEPT_FRAME_SIDE` pixels on their long
/// side, as PNG.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct KeptFrames {
    /// Their times, seconds, increasing (the context frames' clock).
    pub times: Vec<f64>,
    /// Their size, pixels.
    pub width: u32,
    /// Their size, pixels.
    pub height: u32,
}

impl KeptFrames {
    /// Where they live in a clip's directory.
    pub const DIR: &str = "source";

    /// Kept frame `index`'s path inside a clip's directory (also its shared object's name).
    pub fn name(index: usize) -> String {
        format!("{}/{index:03}.png", Self::DIR)
    }
}

impl ClipRecord {
    /// Bytes of the clip's features.
    pub fn feature_bytes(&self) -> u64 {
        self.feature_shape.iter().product::<usize>() as u64 * 4
    }

    /// The source's frame step decodes use: the recorded one, else (a clip stored before it was
    /// recorded) the source's frame period `1 / fps`, else unknown.
    pub fn frame_step(&self) -> Option<f64> {
        let positive = |s: &f64| s.is_finite() && *s > 0.0;
        self.frame_step
            .filter(positive)
            .or_else(|| Some(1.0 / self.source.fps).filter(positive))
    }

    /// The span decode and render accept.
    pub fn span(&self) -> (f64, f64) {
        (
            self.context_times.first().copied().unwrap_or(0.0),
            self.context_times.last().copied().unwrap_or(0.0),
        )
    }
}

/// Seconds since the Unix epoch.
pub fn now() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map(|d| d.as_secs())
        .unwrap_or(0)
}
