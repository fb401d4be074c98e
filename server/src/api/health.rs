//! `/health`: the process answers. `/ready`: the model has loaded and can serve, and the server is
//! not draining (503 `draining` from SIGTERM on, so a load balancer stops sending it requests).

use axum::Json;
use axum::extract::State;
use serde_json::{Value, json};

use crate::AppState;
use crate::error::ErrorReply;
use c4g_service::ServiceError;

pub async fn health() -> Json<Value> {
    Json(json!({ "status": "ok" }))
}

pub async fn ready(State(state): State<AppState>) -> Result<Json<Value>, ErrorReply> {
    if state.is_draining() {
        return Err(ServiceError::Draining.into());
    }
    let service = state.service()?;
    Ok(Json(
        json!({ "status": "ready", "model": service.engine.manifest().name }),
    ))
}
