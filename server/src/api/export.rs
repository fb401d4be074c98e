//! `POST /v1/clips/{id}/export`: the sets over a time range as one file other viewers open, sent
//! as a download (`Content-Disposition: attachment`): a zip of `.ply` or `.spz` files, or a
//! fitted `.splatv` (`service/src/views/exports.rs`).
//!
//! Headers: `X-C4G-Sets` (the sets in the file, or fitted to), and for `.splatv`
//! `X-C4G-Fit-Position-Error` (the fit's largest and RMS position error over those sets, scene
//! units, as `max=…, rms=…`) so that a client sees what the approximation costs.

use axum::extract::State;
use axum::http::header;
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
use c4g_service::sets::streaming::{Spacing, StreamRequest};
use c4g_service::views::exports::ExportFormat;

#[derive(Debug, Clone, Copy, Deserialize)]
#[serde(rename_all = "snake_case")]
enum Format {
    PlyZip,
    SpzZip,
    Splatv,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct Request {
    format: Format,
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
}

pub async fn export(
    State(state): State<AppState>,
    ClipId(id): ClipId,
    JsonBody(body): JsonBody<Value>,
) -> Result<Response, ErrorReply> {
    let service = state.service()?.clone();
    json::check_body(&body, service.limits.max_times)?;
    let request: Request = json::typed(body)?;
    let format = match request.format {
        Format::PlyZip => ExportFormat::PlyZip,
        Format::SpzZip => ExportFormat::SpzZip,
        Format::Splatv => ExportFormat::Splatv,
    };
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
        spacing: Spacing::stated(request.step, request.fps)?,
        quality,
    };
    let export = service.views.export(&id, &stream, format).await?;
    let name: String = id.chars().take(12).collect();
    let mut response = (
        [
            (header::CONTENT_TYPE, format.content_type().to_owned()),
            (
                header::CONTENT_DISPOSITION,
                format!("attachment; filename=\"{name}.{}\"", format.extension()),
            ),
        ],
        export.bytes,
    )
        .into_response();
    let headers = response.headers_mut();
    headers.insert("x-c4g-sets", export.times.len().into());
    if let Some(fit) = export.fit
        && let Ok(value) = format!("max={:e}, rms={:e}", fit.position_max, fit.position_rms).parse()
    {
        headers.insert("x-c4g-fit-position-error", value);
    }
    Ok(scene::label(response, served))
}
