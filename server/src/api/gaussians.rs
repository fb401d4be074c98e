//! `POST /v1/clips/{id}/gaussians`: the Gaussians at one or more times, as JSON, the packed
//! binary format, `.ply` or `.splat`; with `"features": true`, each Gaussian's lifted feature
//! vector too (JSON `features`, `C4GS` version 2, `.ply` `feat_*` properties).

use axum::Json;
use axum::extract::State;
use axum::http::{HeaderMap, header};
use axum::response::{IntoResponse, Response};
use c4g_formats::{ply, splat};
use serde::Deserialize;
use serde_json::Value;

use super::json::{self, ClipId, JsonBody};
use super::scene;
use crate::AppState;
use crate::error::ErrorReply;
use crate::wire::{self, Precision};
use c4g_service::ServiceError;
use c4g_service::sets::keyframes::KeyframesSpec;
use c4g_service::sets::quality::{Preset, PruneSpec, QualitySpec};
use c4g_service::sets::scene::Scene;

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GaussiansRequest {
    t: Option<f64>,
    times: Option<Vec<f64>>,
    format: Option<GaussianFormat>,
    #[serde(default)]
    precision: Precision,
    /// A named speed/accuracy trade: exact (the default), balanced, fast.
    quality: Option<Preset>,
    /// Exact sets at keyframes, interpolated between them (default: the preset's).
    keyframes: Option<KeyframesSpec>,
    /// Drop the Gaussians that change nothing visible (default: the preset's).
    prune: Option<PruneSpec>,
    /// Each Gaussian's lifted feature vector too (a package with a feature decoder only).
    #[serde(default)]
    features: bool,
    /// Which scene: auto (the default), feed-forward or fitted.
    #[serde(default)]
    scene: Scene,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "snake_case")]
enum GaussianFormat {
    Json,
    Binary,
    Ply,
    Splat,
}

impl GaussianFormat {
    fn from_accept(headers: &HeaderMap) -> Option<Self> {
        let accept = headers.get(header::ACCEPT)?.to_str().ok()?;
        [
            ("application/x-c4g-gaussians", Self::Binary),
            ("application/x-ply", Self::Ply),
            ("application/x-splat", Self::Splat),
        ]
        .into_iter()
        .find(|(mime, _)| accept.contains(mime))
        .map(|(_, f)| f)
    }
}

pub async fn decode(
    State(state): State<AppState>,
    ClipId(id): ClipId,
    headers: HeaderMap,
    JsonBody(body): JsonBody<Value>,
) -> Result<Response, ErrorReply> {
    let service = state.service()?;
    json::check_body(&body, service.limits.max_times)?;
    let request: GaussiansRequest = json::typed(body)?;
    let times = match (request.t, request.times) {
        (Some(t), None) => vec![t],
        (None, Some(times)) => times,
        (Some(_), Some(_)) => {
            return Err(ServiceError::invalid("give \"t\" or \"times\", not both").into());
        }
        (None, None) => {
            return Err(
                ServiceError::invalid("give a time: {\"t\": 0.5} or {\"times\": [..]}").into(),
            );
        }
    };
    let format = request
        .format
        .or_else(|| GaussianFormat::from_accept(&headers))
        .unwrap_or(GaussianFormat::Json);
    if matches!(format, GaussianFormat::Ply | GaussianFormat::Splat) && times.len() != 1 {
        return Err(ServiceError::invalid(
            "ply and splat hold one set: ask for one time (or use json or binary)",
        )
        .into());
    }
    if request.features && format == GaussianFormat::Splat {
        return Err(ServiceError::invalid(
            "the .splat format has no room for features: ask for json, binary or ply with \
             \"features\": true",
        )
        .into());
    }
    let mut quality = QualitySpec {
        preset: request.quality,
        keyframes: request.keyframes,
        prune: request.prune,
        scene: request.scene,
    };
    let served = service
        .sets
        .resolve_scene(&id, &mut quality, request.features)
        .await?;
    let frames = if request.features {
        service.views.decode_features(&id, times, quality).await?
    } else {
        service.sets.decode(&id, times, quality).await?
    };
    let response = match format {
        GaussianFormat::Json => Json(wire::json(&frames)).into_response(),
        GaussianFormat::Binary => (
            [(header::CONTENT_TYPE, "application/x-c4g-gaussians")],
            wire::binary(&frames, request.precision)?,
        )
            .into_response(),
        GaussianFormat::Ply => (
            [(header::CONTENT_TYPE, "application/x-ply")],
            ply::encode(&frames[0].1),
        )
            .into_response(),
        GaussianFormat::Splat => (
            [(header::CONTENT_TYPE, "application/x-splat")],
            splat::encode(&frames[0].1),
        )
            .into_response(),
    };
    Ok(scene::label(response, served))
}
