//! `GET /v1/models`: the served model package, as its manifest describes it.

use axum::Json;
use axum::extract::State;
use serde_json::{Value, json};

use crate::{ApiError, AppState};

pub async fn list(State(state): State<AppState>) -> Result<Json<Value>, ApiError> {
    let engine = state.engine().ok_or(ApiError::NotReady)?;
    let m = engine.manifest();
    Ok(Json(json!({
        "models": [{
            "name": m.name,
            "version": m.version,
            "description": m.description,
            "provenance": m.provenance,
            "training": m.training,
            "input": { "width": m.input.width, "height": m.input.height },
            "gaussians_per_set": m.gaussian_count,
            "feature_lifting": m.feature_decoder_width(),
            "time_policy": format!("{:?}", engine.options().time_policy).to_lowercase(),
        }]
    })))
}
