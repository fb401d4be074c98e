//! `POST /v1/clips/{id}/segment`: the Gaussians whose lifted feature is like a clicked pixel's
//! (or a given feature), and their masks at other times (`c4g_service::views::features` says how).

use axum::Json;
use axum::extract::State;
use serde::Deserialize;
use serde_json::Value;

use super::json::{self, ClipId, JsonBody};
use crate::AppState;
use crate::error::ErrorReply;
use c4g_service::ServiceError;
use c4g_service::views::camera::CameraSpec;
use c4g_service::views::features::{Click, Segment, SegmentRequest, Selection};

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SegmentBody {
    click: Option<Click>,
    feature: Option<Vec<f32>>,
    /// With `feature`: when the Gaussians' features are compared with it.
    t: Option<f64>,
    threshold: Option<f32>,
    times: Option<Vec<f64>>,
    camera: Option<CameraSpec>,
    width: Option<u32>,
    height: Option<u32>,
}

pub async fn segment(
    State(state): State<AppState>,
    ClipId(id): ClipId,
    JsonBody(body): JsonBody<Value>,
) -> Result<Json<Segment>, ErrorReply> {
    let service = state.service()?.clone();
    json::check_body(&body, service.limits.max_times)?;
    let body: SegmentBody = json::typed(body)?;
    let selection = match (body.click, body.feature, body.t) {
        (Some(click), None, None) => Selection::Click(click),
        (None, Some(feature), t) => Selection::Feature { feature, t },
        (Some(_), None, Some(_)) => {
            return Err(ServiceError::invalid(
                "a click has its own time (click.t); \"t\" is for a feature selection",
            )
            .into());
        }
        (Some(_), Some(_), _) => {
            return Err(ServiceError::invalid(
                "select by a \"click\" or by a \"feature\", not both",
            )
            .into());
        }
        (None, None, _) => {
            return Err(ServiceError::invalid(
                "give a selection: {\"click\": {\"t\": s, \"x\": px, \"y\": px}} or \
                 {\"feature\": [..]}",
            )
            .into());
        }
    };
    let request = SegmentRequest {
        selection,
        threshold: body.threshold,
        times: body.times,
        camera: body.camera,
        width: body.width,
        height: body.height,
    };
    Ok(Json(service.views.segment(&id, request).await?))
}
