//! `POST /v1/clips/{id}/tracks`: where query points seen in the input frames go at other times,
//! followed by their Gaussians or by feature matching (`c4g_service::views::tracking` says how).

use axum::Json;
use axum::extract::State;
use axum::response::{IntoResponse, Response};
use serde::Deserialize;
use serde_json::Value;

use super::json::{self, ClipId, JsonBody};
use super::scene;
use crate::AppState;
use crate::error::ErrorReply;
use c4g_service::sets::keyframes::KeyframesSpec;
use c4g_service::sets::quality::{Preset, PruneSpec, QualitySpec};
use c4g_service::sets::scene::Scene;
use c4g_service::views::tracking::{TrackQuery, TrackRequest, Tracker};

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TracksRequest {
    queries: Vec<TrackQuery>,
    times: Option<Vec<f64>>,
    width: Option<u32>,
    height: Option<u32>,
    /// A named speed/accuracy trade for the sets the tracks are read from (default exact).
    quality: Option<Preset>,
    keyframes: Option<KeyframesSpec>,
    prune: Option<PruneSpec>,
    /// Which scene: auto (the default), feed-forward or fitted.
    #[serde(default)]
    scene: Scene,
    /// Which tracker follows the points (default: the Gaussians').
    #[serde(default)]
    tracker: Tracker,
}

pub async fn tracks(
    State(state): State<AppState>,
    ClipId(id): ClipId,
    JsonBody(body): JsonBody<Value>,
) -> Result<Response, ErrorReply> {
    let service = state.service()?.clone();
    json::check_body(&body, service.limits.max_times)?;
    let request: TracksRequest = json::typed(body)?;
    let mut quality = QualitySpec {
        preset: request.quality,
        keyframes: request.keyframes,
        prune: request.prune,
        scene: request.scene,
    };
    // The feature tracker follows the feed-forward scene's lifted features, whatever scene
    // holds the Gaussians: resolved as a feature request, so the label says so.
    let features = request.tracker == Tracker::Features;
    let served = service
        .sets
        .resolve_scene(&id, &mut quality, features)
        .await?;
    let request = TrackRequest {
        tracker: request.tracker,
        queries: request.queries,
        times: request.times,
        width: request.width,
        height: request.height,
        quality,
    };
    let tracks = Json(service.views.tracks(&id, request).await?);
    Ok(scene::label(tracks.into_response(), served))
}
