//! Clips: what the server says about an upload, and the calls that describe, list and delete.

use serde::{Deserialize, Serialize};
use serde_json::{Map, Value};

use crate::client::json;
use crate::{Client, Error, FittedSummary};

/// An uploaded clip (`POST /v1/clips`, `GET /v1/clips/{id}`). Fields the client does not name are
/// kept in [`extra`](Self::extra), and optional ones stay absent when the server leaves them out,
/// so a clip re-serialises as the server sent it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Clip {
    /// The clip id, a content address: the same bytes with the same options give the same id.
    pub id: String,
    /// The model that encoded it.
    #[serde(default)]
    pub model: String,
    /// `ready`, or `encoding` while the server works.
    #[serde(default)]
    pub state: String,
    /// Times (seconds) of the context frames the model saw.
    #[serde(default)]
    pub context_times: Vec<f64>,
    /// The context span `[first, last]`: decoding and rendering accept times inside it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub span: Option<[f64; 2]>,
    /// The uploaded media.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub source: Option<ClipSource>,
    /// Size of the cached encoder features.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub feature_bytes: Option<u64>,
    /// On upload: true when this upload created the clip, false when it was already stored.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub created: Option<bool>,
    /// The clip's fitted scene, once a fit made one ([`Client::fit`]): requests serve it by
    /// default.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub fitted: Option<FittedSummary>,
    /// Everything else the server reported.
    #[serde(flatten)]
    pub extra: Map<String, Value>,
}

impl Clip {
    /// The context span: the server's `span`, else the first and last context times.
    pub fn context_span(&self) -> Option<(f64, f64)> {
        match (
            self.span,
            self.context_times.first(),
            self.context_times.last(),
        ) {
            (Some([start, end]), _, _) => Some((start, end)),
            (None, Some(&start), Some(&end)) => Some((start, end)),
            _ => None,
        }
    }
}

/// The media a clip was made from.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ClipSource {
    /// `video` or `images`.
    #[serde(default)]
    pub kind: String,
    /// Frames in the upload (before sampling context frames).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub frames: Option<u64>,
    /// Frame width in pixels.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub width: Option<u32>,
    /// Frame height in pixels.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub height: Option<u32>,
    /// Duration in seconds.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub duration: Option<f64>,
    /// The video's average frame rate, or the fps given for image frames.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub fps: Option<f64>,
    /// Everything else the server reported.
    #[serde(flatten)]
    pub extra: Map<String, Value>,
}

impl Client {
    /// Describes one clip (`GET /v1/clips/{id}`).
    pub async fn clip(&self, clip_id: &str) -> Result<Clip, Error> {
        let url = self.url(&["v1", "clips", clip_id]);
        json(self.send(self.http().get(url)).await?).await
    }

    /// Every stored clip (`GET /v1/clips`).
    pub async fn clips(&self) -> Result<Vec<Clip>, Error> {
        #[derive(Deserialize)]
        struct Clips {
            clips: Vec<Clip>,
        }
        let url = self.url(&["v1", "clips"]);
        Ok(json::<Clips>(self.send(self.http().get(url)).await?)
            .await?
            .clips)
    }

    /// Deletes a clip and its cached features (`DELETE /v1/clips/{id}`).
    pub async fn delete(&self, clip_id: &str) -> Result<(), Error> {
        let url = self.url(&["v1", "clips", clip_id]);
        self.send(self.http().delete(url)).await?;
        Ok(())
    }
}
