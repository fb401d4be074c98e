//! Segments (`POST /v1/clips/{id}/segment`): the Gaussians whose lifted feature is like a clicked
//! pixel's (or a given feature), and their masks at other times, run-length encoded.

use serde::{Deserialize, Serialize};
use serde_json::json;

use crate::client::json;
use crate::{CameraSpec, Client, Error};

/// What a segment is selected by.
#[derive(Debug, Clone, PartialEq)]
pub enum Selection {
    /// The feature the pixel `(x, y)` shows at time `t`.
    Click {
        /// Media time, seconds.
        t: f64,
        /// Pixel column coordinate (pixel `i` covers `[i, i+1)`).
        x: f32,
        /// Pixel row coordinate.
        y: f32,
    },
    /// A feature vector, compared with the Gaussians' features at `t` (default: the clip's first
    /// context time).
    Feature {
        /// The vector (the model's feature width).
        feature: Vec<f32>,
        /// When to compare.
        t: Option<f64>,
    },
}

/// A segment request.
#[derive(Debug, Clone, PartialEq)]
pub struct SegmentRequest {
    /// What to select by.
    pub selection: Selection,
    /// The cosine similarity a Gaussian must reach (server default 0.8).
    pub threshold: Option<f32>,
    /// Where to answer masks (empty: the clip's context times).
    pub times: Vec<f64>,
    /// The camera of the click and masks (default: the input camera at each time).
    pub camera: Option<CameraSpec>,
    /// The image size (default: the model's input size).
    pub size: Option<(u32, u32)>,
}

/// A mask at one time.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Mask {
    /// Media time, seconds.
    pub t: f64,
    /// Pixels set.
    pub area: u64,
    /// Alternating runs over the pixels in row-major order, starting with unset pixels.
    pub counts: Vec<u32>,
}

impl Mask {
    /// The mask as one flag per pixel, row-major.
    pub fn pixels(&self) -> Vec<bool> {
        let mut out = Vec::new();
        for (k, &run) in self.counts.iter().enumerate() {
            out.extend(std::iter::repeat_n(k % 2 == 1, run as usize));
        }
        out
    }
}

/// The server's answer.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Segment {
    /// The masks' width.
    pub width: u32,
    /// Their height.
    pub height: u32,
    /// When the Gaussians' features were compared.
    pub t: f64,
    /// The cosine threshold used.
    pub threshold: f32,
    /// The feature selected by.
    pub feature: Vec<f32>,
    /// The selected Gaussians (the same at every time).
    pub gaussians: Vec<u32>,
    /// One per answered time.
    pub masks: Vec<Mask>,
}

impl Client {
    /// The segment `request` asks for in clip `clip_id`.
    pub async fn segment(&self, clip_id: &str, request: &SegmentRequest) -> Result<Segment, Error> {
        let url = self.url(&["v1", "clips", clip_id, "segment"]);
        let mut body = match &request.selection {
            Selection::Click { t, x, y } => json!({"click": {"t": t, "x": x, "y": y}}),
            Selection::Feature { feature, t } => {
                let mut body = json!({ "feature": feature });
                if let Some(t) = t {
                    body["t"] = json!(t);
                }
                body
            }
        };
        if let Some(threshold) = request.threshold {
            body["threshold"] = json!(threshold);
        }
        if !request.times.is_empty() {
            body["times"] = json!(request.times);
        }
        if let Some(camera) = &request.camera {
            body["camera"] = json!(camera);
        }
        if let Some((width, height)) = request.size {
            body["width"] = json!(width);
            body["height"] = json!(height);
        }
        json(self.send(self.http().post(url).json(&body)).await?).await
    }
}
