//! Errors as the API shows them: over HTTP a status and a JSON body `{"error": ..., "kind": ...}`
//! whose `kind` a client can switch on; over gRPC a status code and the same message. Engine and
//! renderer errors map to statuses here and nowhere else.

use std::time::Duration;

use axum::Json;
use axum::http::{HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use c4g_engine::{EngineError, ErrorKind};
use c4g_renderer::RendererError;
use serde_json::json;

/// An error answered to a client. Messages say what happened and what to do about it.
#[derive(Debug, thiserror::Error)]
pub enum ApiError {
    /// The model is still loading.
    #[error("the model is still loading; retry shortly")]
    NotReady,
    /// The request is malformed or asks for something impossible.
    #[error("{0}")]
    InvalidInput(String),
    /// Missing or wrong API key.
    #[error("missing or wrong API key: send `Authorization: Bearer <key>`")]
    Unauthorized,
    /// Something the request names does not exist.
    #[error("{0}")]
    NotFound(String),
    /// Over a configured limit.
    #[error("{0}")]
    TooLarge(String),
    /// Media of a kind the service does not read.
    #[error("{0}")]
    UnsupportedMedia(String),
    /// Media of a known kind that cannot be read (truncated, corrupt, unusable frames).
    #[error("{0}")]
    UnreadableMedia(String),
    /// Every encode slot is taken.
    #[error("every encode slot is busy; retry in {}s", retry_after.as_secs())]
    Busy {
        /// When to try again.
        retry_after: Duration,
    },
    /// The job queue is full.
    #[error("the server is overloaded; retry in {}s", retry_after.as_secs())]
    Overloaded {
        /// When to try again.
        retry_after: Duration,
    },
    /// The server failed; the message is logged and shown.
    #[error("internal error: {0}")]
    Internal(String),
    /// An engine error, mapped by its kind.
    #[error(transparent)]
    Engine(#[from] EngineError),
    /// A renderer error, mapped by its kind.
    #[error(transparent)]
    Renderer(#[from] RendererError),
}

impl ApiError {
    /// Shorthand for [`ApiError::InvalidInput`].
    pub fn invalid(message: impl Into<String>) -> Self {
        Self::InvalidInput(message.into())
    }

    /// The HTTP status and the machine-readable kind.
    pub fn status_and_kind(&self) -> (StatusCode, &'static str) {
        match self {
            ApiError::NotReady => (StatusCode::SERVICE_UNAVAILABLE, "not_ready"),
            ApiError::InvalidInput(_) => (StatusCode::BAD_REQUEST, "invalid_input"),
            ApiError::Unauthorized => (StatusCode::UNAUTHORIZED, "unauthorized"),
            ApiError::NotFound(_) => (StatusCode::NOT_FOUND, "not_found"),
            ApiError::TooLarge(_) => (StatusCode::PAYLOAD_TOO_LARGE, "too_large"),
            ApiError::UnsupportedMedia(_) => {
                (StatusCode::UNSUPPORTED_MEDIA_TYPE, "unsupported_media")
            }
            ApiError::UnreadableMedia(_) => (StatusCode::UNPROCESSABLE_ENTITY, "unreadable_media"),
            ApiError::Busy { .. } => (StatusCode::TOO_MANY_REQUESTS, "busy"),
            ApiError::Overloaded { .. } => (StatusCode::SERVICE_UNAVAILABLE, "overloaded"),
            ApiError::Internal(_) => (StatusCode::INTERNAL_SERVER_ERROR, "internal"),
            ApiError::Engine(e) => match e.kind() {
                ErrorKind::InvalidInput => (StatusCode::BAD_REQUEST, "invalid_input"),
                ErrorKind::Unsupported => (StatusCode::UNPROCESSABLE_ENTITY, "unsupported"),
                ErrorKind::Package | ErrorKind::Runtime | ErrorKind::ModelOutput => {
                    (StatusCode::INTERNAL_SERVER_ERROR, "internal")
                }
            },
            ApiError::Renderer(e) => match e {
                RendererError::ThreadPool(_)
                | RendererError::Io { .. }
                | RendererError::GpuUnavailable(_)
                | RendererError::Gpu(_)
                | RendererError::InvalidGaussian { .. } => {
                    (StatusCode::INTERNAL_SERVER_ERROR, "internal")
                }
                _ => (StatusCode::BAD_REQUEST, "invalid_input"),
            },
        }
    }

    fn retry_after(&self) -> Option<Duration> {
        match self {
            ApiError::Busy { retry_after } | ApiError::Overloaded { retry_after } => {
                Some(*retry_after)
            }
            ApiError::NotReady => Some(Duration::from_secs(1)),
            _ => None,
        }
    }

    fn log(&self, status: StatusCode) {
        if status.is_server_error()
            && !matches!(self, ApiError::NotReady | ApiError::Overloaded { .. })
        {
            tracing::error!(error = %self, "request failed");
        }
    }
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        let (status, kind) = self.status_and_kind();
        self.log(status);
        let mut response = (
            status,
            Json(json!({ "error": self.to_string(), "kind": kind })),
        )
            .into_response();
        if let Some(after) = self.retry_after() {
            response.headers_mut().insert(
                header::RETRY_AFTER,
                HeaderValue::from(after.as_secs().max(1)),
            );
        }
        response
    }
}

impl From<ApiError> for tonic::Status {
    fn from(error: ApiError) -> Self {
        use tonic::Code;
        let (status, kind) = error.status_and_kind();
        error.log(status);
        let code = match status {
            StatusCode::BAD_REQUEST | StatusCode::UNPROCESSABLE_ENTITY => Code::InvalidArgument,
            StatusCode::UNSUPPORTED_MEDIA_TYPE => Code::InvalidArgument,
            StatusCode::UNAUTHORIZED => Code::Unauthenticated,
            StatusCode::NOT_FOUND => Code::NotFound,
            StatusCode::PAYLOAD_TOO_LARGE | StatusCode::TOO_MANY_REQUESTS => {
                Code::ResourceExhausted
            }
            StatusCode::SERVICE_UNAVAILABLE => Code::Unavailable,
            _ => Code::Internal,
        };
        let mut status = tonic::Status::new(code, error.to_string());
        if let Ok(kind) = kind.parse() {
            status.metadata_mut().insert("c4g-error-kind", kind);
        }
        if let Some(after) = error.retry_after()
            && let Ok(value) = after.as_secs().max(1).to_string().parse()
        {
            status.metadata_mut().insert("retry-after", value);
        }
        status
    }
}
