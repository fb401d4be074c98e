//! `POST /v1/clips/{id}/cameras/recover`: each context frame's camera recovered by photometric
//! alignment of the model's own Gaussians (`crate::recovery` says how), kept with the clip.

use axum::Json;
use axum::extract::State;
use serde_json::Value;

use super::json::{self, ClipId, JsonBody};
use crate::recovery::{RecoverOptions, RecoveredCameras};
use crate::{AppState, ServiceError};

pub async fn recover(
    State(state): State<AppState>,
    ClipId(id): ClipId,
    JsonBody(body): JsonBody<Value>,
) -> Result<Json<RecoveredCameras>, ServiceError> {
    let service = state.service()?.clone();
    let options: RecoverOptions = json::typed(body)?;
    Ok(Json(service.recover_cameras(&id, options).await?))
}
