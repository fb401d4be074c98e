//! Rendering (`POST /v1/clips/{id}/render`): one image from one camera at one time, or a video
//! along a camera trajectory.
//!
//! [`Client::render`] takes any serialisable request, so a [`RenderRequest`] and a hand-written
//! `serde_json::Value` both work; fields the typed request leaves `None` are not sent, and the
//! server's defaults apply (the first context camera, the model's intrinsics and input size).

use std::fmt;

use bytes::Bytes;
use reqwest::header::CONTENT_TYPE;
use serde::{Deserialize, Serialize};

use crate::quality::served_scene;
use crate::{Approximation, Client, Error, Scene};

/// A render request, as `docs/api.md` describes its JSON.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct RenderRequest {
    /// Media time (seconds) of a single image; required unless a trajectory is given.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub t: Option<f64>,
    /// The camera (for a trajectory: the camera the preset moves around).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub camera: Option<CameraSpec>,
    /// Image width in pixels (default: the model's input width).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub width: Option<u32>,
    /// Image height in pixels (default: the model's input height).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub height: Option<u32>,
    /// RGB background, 0..1 (default black).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub background: Option<[f32; 3]>,
    /// Output format (default `png` for an image, `mp4` for a trajectory).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub format: Option<RenderFormat>,
    /// A trajectory preset: makes the request a video. JSON rather than [`TrajectoryPreset`] so
    /// presets this client does not know pass through; build one with
    /// [`TrajectoryPreset::to_json`].
    #[serde(skip_serializing_if = "Option::is_none")]
    pub trajectory: Option<serde_json::Value>,
    /// Frames of a trajectory video (server default 24).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub frames: Option<u32>,
    /// First time of a trajectory video (default: the context span's start).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub start: Option<f64>,
    /// Last time of a trajectory video (default: the context span's end).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub end: Option<f64>,
    /// Frame rate of a trajectory video (server default 12).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub fps: Option<f64>,
    /// A quality preset, keyframes (a trajectory's only), pruning (default: exact).
    #[serde(flatten)]
    pub approximation: Approximation,
}

/// A camera: a pose and intrinsics, each defaulting to the first context camera's.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct CameraSpec {
    /// Row-major 4×4 world-to-camera matrix (OpenCV axes), last row `0 0 0 1`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub world_to_camera: Option<[f32; 16]>,
    /// Intrinsics as fractions of the image size.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub intrinsics: Option<IntrinsicsSpec>,
}

/// Pinhole intrinsics as fractions of the image size (the model's default: fx = fy = 0.8767,
/// principal point centred).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct IntrinsicsSpec {
    /// Focal length in x, as a fraction of the width.
    pub fx: f32,
    /// Focal length in y, as a fraction of the height.
    pub fy: f32,
    /// Principal point x, as a fraction of the width.
    pub cx: f32,
    /// Principal point y, as a fraction of the height.
    pub cy: f32,
}

/// What a render produces.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum RenderFormat {
    /// RGB PNG.
    Png,
    /// Raw little-endian `f32` expected depth, row-major.
    Depth,
    /// Raw little-endian `f32` accumulated opacity, row-major.
    Alpha,
    /// H.264 video (trajectories).
    Mp4,
    /// Raw little-endian `f32` lifted features, `[H, W, F]` (`X-C4G-Channels` is F).
    Features,
    /// The lifted features coloured by the clip's PCA basis, RGB PNG.
    FeaturesPca,
}

impl RenderFormat {
    /// The API's name.
    pub fn as_str(self) -> &'static str {
        match self {
            RenderFormat::Png => "png",
            RenderFormat::Depth => "depth",
            RenderFormat::Alpha => "alpha",
            RenderFormat::Mp4 => "mp4",
            RenderFormat::Features => "features",
            RenderFormat::FeaturesPca => "features_pca",
        }
    }
}

impl fmt::Display for RenderFormat {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

/// The camera trajectory presets of `docs/api.md`, each moving around the request's camera.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "lowercase")]
pub enum TrajectoryPreset {
    /// Swing left and right around a point `depth` ahead, by up to `angle_degrees`.
    Orbit {
        /// Distance to the point orbited, in scene units.
        depth: f64,
        /// Largest swing, degrees.
        angle_degrees: f64,
    },
    /// A spiral around the camera, looking at a point `focus_depth` ahead.
    Spiral {
        /// Radii in x, y, z.
        radii: [f64; 3],
        /// Distance to the point looked at.
        focus_depth: f64,
        /// Turns over the video.
        rotations: f64,
        /// Rate of the z motion.
        z_rate: f64,
    },
    /// Move forward by `distance`.
    Dolly {
        /// How far to move, in scene units.
        distance: f64,
    },
}

impl TrajectoryPreset {
    /// The preset as the request's `trajectory` field.
    pub fn to_json(&self) -> serde_json::Value {
        serde_json::to_value(self).unwrap_or_default()
    }
}

/// A rendered image or video.
#[derive(Debug, Clone, PartialEq)]
pub struct Rendered {
    /// The bytes: PNG, MP4, or raw `f32` (depth and alpha).
    pub data: Bytes,
    /// The answer's media type.
    pub content_type: String,
    /// Image width, when the server said (`X-C4G-Width`; always for depth and alpha).
    pub width: Option<u32>,
    /// Image height, when the server said (`X-C4G-Height`).
    pub height: Option<u32>,
    /// Floats a pixel of a raw feature image (`X-C4G-Channels`).
    pub channels: Option<u32>,
    /// The scene that served it (`X-C4G-Scene`: feed-forward or fitted).
    pub scene: Option<Scene>,
}

impl Client {
    /// Renders a clip: an image, or a video when the request has a trajectory.
    pub async fn render<R: Serialize + ?Sized>(
        &self,
        clip_id: &str,
        request: &R,
    ) -> Result<Rendered, Error> {
        let url = self.url(&["v1", "clips", clip_id, "render"]);
        let response = self.send(self.http().post(url).json(request)).await?;
        let headers = response.headers();
        let number = |name: &str| {
            headers
                .get(name)
                .and_then(|v| v.to_str().ok())
                .and_then(|v| v.trim().parse().ok())
        };
        let width = number("x-c4g-width");
        let height = number("x-c4g-height");
        let channels = number("x-c4g-channels");
        let scene = served_scene(headers);
        let content_type = headers
            .get(CONTENT_TYPE)
            .and_then(|v| v.to_str().ok())
            .unwrap_or("application/octet-stream")
            .to_owned();
        Ok(Rendered {
            data: response.bytes().await?,
            content_type,
            width,
            height,
            channels,
            scene,
        })
    }
}
