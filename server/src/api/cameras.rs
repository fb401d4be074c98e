//! `POST /v1/clips/{id}/cameras/recover`: each context frame's camera recovered by photometric
//! alignment of the model's own Gaussians (`c4g_service::views::recovery` says how), kept with the clip.

use axum::Json;
use axum::extract::State;
use serde_json::Value;

use super::json::{self, ClipId, JsonBody};
use crate::AppState;
use crate::error::ErrorReply;
use c4g_service::views::recovery::{RecoverOptions, RecoveredCameras};

pub async fn recover(
    State(state): State<AppState>,
    ClipId(id): ClipId,
    JsonBody(body): JsonBody<Value>,
) -> Result<Json<RecoveredCameras>, ErrorReply> {
    let service = state.service()?.clone();
    let options: RecoverOptions = json::typed(body)?;
    Ok(Json(service.views.recover_cameras(&id, options).await?))
}
