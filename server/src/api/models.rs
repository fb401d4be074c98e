//! `GET /v1/models`: the served model package, as its manifest describes it.

use axum::Json;
use axum::extract::State;
use serde_json::{Value, json};

use crate::AppState;
use crate::error::ErrorReply;
use c4g_service::service::Service;

pub async fn list(State(state): State<AppState>) -> Result<Json<Value>, ErrorReply> {
    let service = state.service()?;
    Ok(Json(json!({ "models": [describe(service)] })))
}

/// The model as `/v1/models` and gRPC `ListModels` describe it.
pub fn describe(service: &Service) -> Value {
    let engine = &service.engine;
    let m = engine.manifest();
    json!({
        "name": m.name,
        "version": m.version,
        "description": m.description,
        "provenance": m.provenance,
        "training": m.training,
        "input": { "width": m.input.width, "height": m.input.height },
        "gaussians_per_set": m.gaussian_count,
        "feature_lifting": m.feature_decoder_width(),
        "time_policy": engine.time_policy().name(),
        "renderer": service.views.renderer.name(),
        // Which pixels a Gaussian reaches in this server's renders: what a client that
        // rasterizes sets itself (the viewer) needs to draw the same image.
        "footprint": service.views.renderer.footprint().as_str(),
        "store_key": service.model_key(),
        "limits": {
            "context_frames": service.limits.context_frames,
            "max_context_frames": service.limits.max_context_frames,
            "max_body_bytes": service.limits.max_body_bytes,
            "max_source_frames": service.limits.max_source_frames,
            "max_duration_s": service.limits.max_duration_s,
            "max_side": service.limits.max_side,
            "min_side": service.limits.min_side,
            "max_render_pixels": service.limits.max_render_pixels,
            "max_times": service.limits.max_times,
        },
    })
}
