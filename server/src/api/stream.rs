//! `POST /v1/clips/{id}/stream`: the sets over a time range as one compact 4D stream (`C4GV`,
//! `application/x-c4g-stream`), in a chunked HTTP body that a browser reads as it arrives.
//!
//! Chunked HTTP rather than a WebSocket: the data flows one way, `fetch()` hands a page the body
//! piece by piece (`response.body.getReader()`), aborting the fetch ends the decoding (the reader
//! is gone, so the next set is not decoded), HTTP/1.1 proxies pass it as they are, and the errors
//! before the first byte (the first set is made before the headers go) are the service's usual
//! JSON answers. An error after the first byte
//! cannot change the status: the body then ends without the stream's index record, which a
//! reader sees as a stream cut short (and the server logs why).

use axum::body::Body;
use axum::extract::State;
use axum::http::header;
use axum::response::{IntoResponse, Response};
use c4g_formats::c4gv::EncodeOptions;
use futures_util::StreamExt;
use serde::Deserialize;
use serde_json::Value;

use super::json::{self, ClipId, JsonBody};
use super::scene;
use crate::AppState;
use crate::error::ErrorReply;
use c4g_service::sets::keyframes::KeyframesSpec;
use c4g_service::sets::quality::{Preset, PruneSpec, QualitySpec};
use c4g_service::sets::scene::Scene;
use c4g_service::sets::streaming::{self, Spacing, StreamRequest, check_compact};

/// The stream's content type.
pub const CONTENT_TYPE: &str = "application/x-c4g-stream";

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct Request {
    start: Option<f64>,
    end: Option<f64>,
    /// Seconds between sets (or `fps`; default the clip's frame rate).
    step: Option<f64>,
    fps: Option<f64>,
    quality: Option<Preset>,
    keyframes: Option<KeyframesSpec>,
    prune: Option<PruneSpec>,
    /// Which scene: auto (the default), feed-forward or fitted.
    #[serde(default)]
    scene: Scene,
    /// The largest error of a position coordinate, scene units (default 1e-3).
    position_error: Option<f64>,
    /// A full set every this many sets, for seeking (default 16).
    keyframe_interval: Option<u32>,
}

pub async fn stream(
    State(state): State<AppState>,
    ClipId(id): ClipId,
    JsonBody(body): JsonBody<Value>,
) -> Result<Response, ErrorReply> {
    let service = state.service()?.clone();
    json::check_body(&body, service.limits.max_times)?;
    let request: Request = json::typed(body)?;
    let spacing = Spacing::stated(request.step, request.fps)?;
    let defaults = EncodeOptions::default();
    let options = EncodeOptions {
        position_error: request.position_error.unwrap_or(defaults.position_error),
        keyframe_interval: request
            .keyframe_interval
            .unwrap_or(defaults.keyframe_interval),
        ..defaults
    };
    check_compact(&options)?;
    let mut quality = QualitySpec {
        preset: request.quality,
        keyframes: request.keyframes,
        prune: request.prune,
        scene: request.scene,
    };
    let served = service.sets.resolve_scene(&id, &mut quality, false).await?;
    let stream = StreamRequest {
        start: request.start,
        end: request.end,
        spacing,
        quality,
    };
    let sets = streaming::stream(&service.sets, &id, &stream).await?;
    let count = sets.times.len();
    // The first set goes out with the headers: a stream that cannot even begin (a first set beyond
    // the stream's range at this position error, for instance) is then the usual JSON error, and
    // only a failure later in the stream cuts a 200 body short.
    let mut pieces = Box::pin(sets.compact(options));
    let first = match pieces.next().await {
        Some(piece) => Some(piece?),
        None => None,
    };
    let body = futures_util::stream::iter(first.map(Ok))
        .chain(pieces)
        .map(move |piece| {
            piece.map(|(_, bytes)| bytes).map_err(|e| {
                tracing::warn!(clip = %id, "a compact stream ended early: {e}");
                std::io::Error::other(e.to_string())
            })
        });
    let response = (
        [
            (header::CONTENT_TYPE, CONTENT_TYPE.to_owned()),
            (
                header::HeaderName::from_static("x-c4g-sets"),
                count.to_string(),
            ),
        ],
        Body::from_stream(body),
    )
        .into_response();
    Ok(scene::label(response, served))
}
