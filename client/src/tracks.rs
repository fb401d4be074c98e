//! Point tracks (`POST /v1/clips/{id}/tracks`): where points seen in the input frames go at
//! other times, read off the clip's Gaussian trajectories.

use serde::{Deserialize, Serialize};
use serde_json::json;

use crate::client::json;
use crate::quality::served_scene;
use crate::{Approximation, Client, Error, Scene};

/// A point seen at pixel `(x, y)` of the input frame at time `t` (pixel `(i, j)` covers
/// `[i, i+1) × [j, j+1)`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct TrackQuery {
    /// Media time, seconds.
    pub t: f64,
    /// Pixel column coordinate.
    pub x: f32,
    /// Pixel row coordinate.
    pub y: f32,
}

/// Which tracker follows the points.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Tracker {
    /// The Gaussians that explain a query's pixel carry it (the server's default).
    #[default]
    Gaussians,
    /// A point is where the rendered feature field matches its feature best (a package with a
    /// feature decoder only).
    Features,
}

/// What to track, and where to answer.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct TrackRequest {
    /// The tracker (`None`: the server's default, the Gaussians').
    pub tracker: Option<Tracker>,
    /// The points.
    pub queries: Vec<TrackQuery>,
    /// The times to answer at (empty: the clip's context times).
    pub times: Vec<f64>,
    /// The image size the points are stated in (default: the model's input size).
    pub size: Option<(u32, u32)>,
    /// How the sets are decoded (default: exact).
    pub approximation: Approximation,
}

/// One point at one time.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct TrackPoint {
    /// Media time, seconds.
    pub t: f64,
    /// Pixel coordinates in the input camera at `t`.
    pub x: f32,
    /// Likewise, rows.
    pub y: f32,
    /// In front of the camera, inside the image and not behind the rendered surface.
    pub visible: bool,
    /// Camera-space depth.
    pub depth: f32,
    /// The 3D point in the model's frame.
    pub position: [f32; 3],
    /// The feature tracker's: the match's cosine similarity with the query's feature.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub similarity: Option<f32>,
}

/// One query's track.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Track {
    /// The query as asked.
    pub query: TrackQuery,
    /// False when nothing covers the query pixel (then `points` is empty).
    pub anchored: bool,
    /// The point at each answered time.
    pub points: Vec<TrackPoint>,
}

/// The server's answer.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Tracks {
    /// The tracker that followed the points.
    #[serde(default)]
    pub tracker: Tracker,
    /// The image size positions are in.
    pub width: u32,
    /// Likewise.
    pub height: u32,
    /// The answered times.
    pub times: Vec<f64>,
    /// One per query, in order.
    pub tracks: Vec<Track>,
    /// The scene the tracks were read from (the answer's `X-C4G-Scene` header, not its body).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub scene: Option<Scene>,
}

impl Client {
    /// Tracks `request`'s points through clip `clip_id`.
    pub async fn tracks(&self, clip_id: &str, request: &TrackRequest) -> Result<Tracks, Error> {
        let url = self.url(&["v1", "clips", clip_id, "tracks"]);
        let mut body = json!(request.approximation);
        body["queries"] = json!(request.queries);
        if let Some(tracker) = request.tracker {
            body["tracker"] = json!(tracker);
        }
        if !request.times.is_empty() {
            body["times"] = json!(request.times);
        }
        if let Some((width, height)) = request.size {
            body["width"] = json!(width);
            body["height"] = json!(height);
        }
        let response = self.send(self.http().post(url).json(&body)).await?;
        let scene = served_scene(response.headers());
        let tracks: Tracks = json(response).await?;
        Ok(Tracks { scene, ..tracks })
    }
}
