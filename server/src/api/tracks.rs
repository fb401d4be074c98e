//! `POST /v1/clips/{id}/tracks`: where query points seen in the input frames go at other times,
//! followed by their Gaussians or by feature matching (`c4g_service::views::tracking` says how).

use axum::Json;
use axum::extract::State;
use serde::Deserialize;
use serde_json::Value;

use super::json::{self, ClipId, JsonBody};
use crate::AppState;
use crate::error::ErrorReply;
use c4g_service::sets::keyframes::KeyframesSpec;
use c4g_service::sets::quality::{Preset, PruneSpec, QualitySpec};
use c4g_service::views::tracking::{TrackQuery, TrackRequest, Tracker, Tracks};

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
    /// Which tracker follows the points (default: the Gaussians').
    #[serde(default)]
    tracker: Tracker,
}

pub async fn tracks(
    State(state): State<AppState>,
    ClipId(id): ClipId,
    JsonBody(body): JsonBody<Value>,
) -> Result<Json<Tracks>, ErrorReply> {
    let service = state.service()?.clone();
    json::check_body(&body, service.limits.max_times)?;
    let request: TracksRequest = json::typed(body)?;
    let request = TrackRequest {
        tracker: request.tracker,
        queries: request.queries,
        times: request.times,
        width: request.width,
        height: request.height,
        quality: QualitySpec {
            preset: request.quality,
            keyframes: request.keyframes,
            prune: request.prune,
        },
    };
    Ok(Json(service.views.tracks(&id, request).await?))
}
