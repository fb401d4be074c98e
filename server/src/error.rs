//! Errors as the API shows them: a status and a JSON body `{"error": ..., "kind": ...}` whose
//! `kind` a client can switch on. Engine errors map to statuses here and nowhere else.

use axum::Json;
use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};
use c4g_engine::{EngineError, ErrorKind};
use serde_json::json;

/// An error answered to a client.
#[derive(Debug, thiserror::Error)]
pub enum ApiError {
    /// The model is still loading.
    #[error("the model is still loading; retry shortly")]
    NotReady,
    /// An engine error, mapped by its kind.
    #[error(transparent)]
    Engine(#[from] EngineError),
}

impl ApiError {
    fn status_and_kind(&self) -> (StatusCode, &'static str) {
        match self {
            ApiError::NotReady => (StatusCode::SERVICE_UNAVAILABLE, "not_ready"),
            ApiError::Engine(e) => match e.kind() {
                ErrorKind::InvalidInput => (StatusCode::BAD_REQUEST, "invalid_input"),
                ErrorKind::Unsupported => (StatusCode::UNPROCESSABLE_ENTITY, "unsupported"),
                ErrorKind::Package | ErrorKind::Runtime | ErrorKind::ModelOutput => {
                    (StatusCode::INTERNAL_SERVER_ERROR, "internal")
                }
            },
        }
    }
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        let (status, kind) = self.status_and_kind();
        if status.is_server_error() {
            tracing::error!(error = %self, "request failed");
        }
        (
            status,
            Json(json!({ "error": self.to_string(), "kind": kind })),
        )
            .into_response()
    }
}
