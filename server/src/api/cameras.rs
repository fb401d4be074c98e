//! `POST /v1/clips/{id}/cameras/recover`: each context frame's camera recovered by photometric
//! alignment of the model's own Gaussians (`c4g_service::views::recovery` says how), kept with the clip;
//! `GET /v1/clips/{id}/cameras?format=json|colmap|transforms`: the clip's cameras as files other
//! tools open (`c4g_service::views::camera_files`).

use axum::Json;
use axum::extract::{RawQuery, State};
use axum::http::header;
use axum::response::{IntoResponse, Response};
use serde_json::Value;

use super::json::{self, ClipId, JsonBody};
use crate::AppState;
use crate::error::ErrorReply;
use c4g_service::ServiceError;
use c4g_service::clips::intake::cameras::CameraFormat;
use c4g_service::quoted;
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

pub async fn files(
    State(state): State<AppState>,
    ClipId(id): ClipId,
    RawQuery(query): RawQuery,
) -> Result<Response, ErrorReply> {
    let format = camera_format(query.as_deref())?;
    let file = state.service()?.views.camera_file(&id, format).await?;
    let disposition = format!("attachment; filename=\"{}\"", file.file_name);
    Ok((
        [
            (header::CONTENT_TYPE, file.content_type.to_owned()),
            (header::CONTENT_DISPOSITION, disposition),
        ],
        file.bytes,
    )
        .into_response())
}

/// `?format=json|colmap|transforms` (default json); other query parameters are ignored.
fn camera_format(query: Option<&str>) -> Result<CameraFormat, ServiceError> {
    let mut format = CameraFormat::Json;
    for (key, value) in json::query_pairs(query)? {
        if key == "format" {
            format = match value.as_str() {
                "json" => CameraFormat::Json,
                "colmap" => CameraFormat::Colmap,
                "transforms" => CameraFormat::Transforms,
                other => {
                    return Err(ServiceError::invalid(format!(
                        "format must be json, colmap or transforms, got {}",
                        quoted(other)
                    )));
                }
            };
        }
    }
    Ok(format)
}
