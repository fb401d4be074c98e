//! The one place where errors become statuses: a [`ServiceError`]'s kind is an HTTP status with a
//! JSON body `{"error": ..., "kind": ...}`, and a gRPC code with the message and a
//! `c4g-error-kind` metadata entry holding the same kind. Both matches are exhaustive, so a new
//! kind does not compile until each transport has a status for it.
//!
//! [`ServiceError`] is the core's (`c4g-service` knows no transport), so REST answers it through
//! [`ErrorReply`] and gRPC through [`status`]: one conversion each, both here.

use axum::Json;
use axum::http::{HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use serde_json::json;
use tonic::Code;

use c4g_service::{ServiceError, ServiceErrorKind};

/// The gRPC metadata entry that carries the error kind.
pub const GRPC_KIND_KEY: &str = "c4g-error-kind";

/// The HTTP status of each kind.
pub fn http_status(kind: ServiceErrorKind) -> StatusCode {
    use ServiceErrorKind as K;
    match kind {
        K::NotReady | K::Draining | K::Overloaded | K::Unavailable => {
            StatusCode::SERVICE_UNAVAILABLE
        }
        K::InvalidInput => StatusCode::BAD_REQUEST,
        K::Unauthorized => StatusCode::UNAUTHORIZED,
        K::NotFound => StatusCode::NOT_FOUND,
        K::TooLarge => StatusCode::PAYLOAD_TOO_LARGE,
        K::UnsupportedMedia => StatusCode::UNSUPPORTED_MEDIA_TYPE,
        K::UnreadableMedia | K::Unsupported => StatusCode::UNPROCESSABLE_ENTITY,
        K::Busy => StatusCode::TOO_MANY_REQUESTS,
        K::InsufficientStorage => StatusCode::INSUFFICIENT_STORAGE,
        K::TimedOut => StatusCode::REQUEST_TIMEOUT,
        K::Internal => StatusCode::INTERNAL_SERVER_ERROR,
    }
}

/// The gRPC code of each kind.
pub fn grpc_code(kind: ServiceErrorKind) -> Code {
    use ServiceErrorKind as K;
    match kind {
        K::NotReady | K::Draining | K::Overloaded | K::Unavailable => Code::Unavailable,
        K::InvalidInput | K::UnsupportedMedia | K::UnreadableMedia | K::Unsupported => {
            Code::InvalidArgument
        }
        K::Unauthorized => Code::Unauthenticated,
        K::NotFound => Code::NotFound,
        K::TooLarge | K::Busy | K::InsufficientStorage => Code::ResourceExhausted,
        K::TimedOut => Code::DeadlineExceeded,
        K::Internal => Code::Internal,
    }
}

/// Server failures are logged where they are answered, and so is a full disk (the operator has
/// to act); refusals for load are expected and are counted by the metrics instead.
fn log(error: &ServiceError, kind: ServiceErrorKind) {
    match kind {
        ServiceErrorKind::Internal => tracing::error!(error = %error, "request failed"),
        ServiceErrorKind::Unavailable => {
            tracing::error!(error = %error, "request failed: a service it needs is down")
        }
        ServiceErrorKind::InsufficientStorage => {
            tracing::error!(error = %error, "request refused: the disk is full")
        }
        _ => {}
    }
}

/// A [`ServiceError`] as a REST handler answers it: handlers return `Result<_, ErrorReply>`, and
/// `?` turns the core's errors into it.
#[derive(Debug)]
pub struct ErrorReply(pub ServiceError);

impl From<ServiceError> for ErrorReply {
    fn from(error: ServiceError) -> Self {
        Self(error)
    }
}

impl IntoResponse for ErrorReply {
    fn into_response(self) -> Response {
        let Self(error) = self;
        let kind = error.kind();
        log(&error, kind);
        let mut response = (
            http_status(kind),
            Json(json!({ "error": error.to_string(), "kind": kind.name() })),
        )
            .into_response();
        if let Some(after) = error.retry_after() {
            response.headers_mut().insert(
                header::RETRY_AFTER,
                HeaderValue::from(after.as_secs().max(1)),
            );
        }
        response
    }
}

/// A [`ServiceError`] as a gRPC method answers it (`.map_err(status)`).
pub fn status(error: ServiceError) -> tonic::Status {
    let kind = error.kind();
    log(&error, kind);
    let mut status = tonic::Status::new(grpc_code(kind), error.to_string());
    status.metadata_mut().insert(
        GRPC_KIND_KEY,
        tonic::metadata::MetadataValue::from_static(kind.name()),
    );
    if let Some(after) = error.retry_after()
        && let Ok(value) = after.as_secs().max(1).to_string().parse()
    {
        status.metadata_mut().insert("retry-after", value);
    }
    status
}

/// [`status`] as a method, for a gRPC method's `return Err(error.into_status())`.
pub trait IntoStatus {
    /// The error as its gRPC status.
    fn into_status(self) -> tonic::Status;
}

impl IntoStatus for ServiceError {
    fn into_status(self) -> tonic::Status {
        status(self)
    }
}

#[cfg(test)]
mod tests {
    use std::collections::HashSet;
    use std::time::Duration;

    use super::*;

    /// Every kind, its name, HTTP status and gRPC code: the contract `docs/api.md` documents.
    const TABLE: [(ServiceErrorKind, &str, u16, Code); 15] = [
        (
            ServiceErrorKind::NotReady,
            "not_ready",
            503,
            Code::Unavailable,
        ),
        (
            ServiceErrorKind::Draining,
            "draining",
            503,
            Code::Unavailable,
        ),
        (
            ServiceErrorKind::InvalidInput,
            "invalid_input",
            400,
            Code::InvalidArgument,
        ),
        (
            ServiceErrorKind::Unauthorized,
            "unauthorized",
            401,
            Code::Unauthenticated,
        ),
        (ServiceErrorKind::NotFound, "not_found", 404, Code::NotFound),
        (
            ServiceErrorKind::TooLarge,
            "too_large",
            413,
            Code::ResourceExhausted,
        ),
        (
            ServiceErrorKind::UnsupportedMedia,
            "unsupported_media",
            415,
            Code::InvalidArgument,
        ),
        (
            ServiceErrorKind::UnreadableMedia,
            "unreadable_media",
            422,
            Code::InvalidArgument,
        ),
        (
            ServiceErrorKind::Unsupported,
            "unsupported",
            422,
            Code::InvalidArgument,
        ),
        (ServiceErrorKind::Busy, "busy", 429, Code::ResourceExhausted),
        (
            ServiceErrorKind::Overloaded,
            "overloaded",
            503,
            Code::Unavailable,
        ),
        (
            ServiceErrorKind::InsufficientStorage,
            "insufficient_storage",
            507,
            Code::ResourceExhausted,
        ),
        (
            ServiceErrorKind::TimedOut,
            "timed_out",
            408,
            Code::DeadlineExceeded,
        ),
        (
            ServiceErrorKind::Unavailable,
            "unavailable",
            503,
            Code::Unavailable,
        ),
        (ServiceErrorKind::Internal, "internal", 500, Code::Internal),
    ];

    #[test]
    fn every_kind_has_its_documented_name_http_status_and_grpc_code() {
        let listed: HashSet<_> = TABLE.iter().map(|row| row.0).collect();
        let all: HashSet<_> = ServiceErrorKind::ALL.into_iter().collect();
        assert_eq!(listed, all, "the table and ServiceErrorKind::ALL disagree");
        assert_eq!(all.len(), ServiceErrorKind::ALL.len(), "ALL repeats a kind");
        for (kind, name, http, code) in TABLE {
            assert_eq!(kind.name(), name);
            assert_eq!(http_status(kind).as_u16(), http, "{name}");
            assert_eq!(grpc_code(kind), code, "{name}");
        }
    }

    #[test]
    fn all_lists_every_variant() {
        // Adding a kind breaks this match until it is given a place in ALL (and so in TABLE).
        for kind in ServiceErrorKind::ALL {
            let position = match kind {
                ServiceErrorKind::NotReady => 0,
                ServiceErrorKind::Draining => 1,
                ServiceErrorKind::InvalidInput => 2,
                ServiceErrorKind::Unauthorized => 3,
                ServiceErrorKind::NotFound => 4,
                ServiceErrorKind::TooLarge => 5,
                ServiceErrorKind::UnsupportedMedia => 6,
                ServiceErrorKind::UnreadableMedia => 7,
                ServiceErrorKind::Unsupported => 8,
                ServiceErrorKind::Busy => 9,
                ServiceErrorKind::Overloaded => 10,
                ServiceErrorKind::InsufficientStorage => 11,
                ServiceErrorKind::TimedOut => 12,
                ServiceErrorKind::Unavailable => 13,
                ServiceErrorKind::Internal => 14,
            };
            assert_eq!(ServiceErrorKind::ALL[position], kind);
        }
    }

    #[test]
    fn grpc_refusals_carry_the_kind_and_the_retry_hint() {
        let refusal = status(ServiceError::Overloaded {
            retry_after: Duration::from_secs(3),
        });
        assert_eq!(refusal.code(), Code::Unavailable);
        let metadata = refusal.metadata();
        assert_eq!(metadata.get(GRPC_KIND_KEY).unwrap(), "overloaded");
        assert_eq!(metadata.get("retry-after").unwrap(), "3");
        let refusal = status(ServiceError::invalid("bad times"));
        assert_eq!(refusal.code(), Code::InvalidArgument);
        assert_eq!(refusal.message(), "bad times");
        assert_eq!(
            refusal.metadata().get(GRPC_KIND_KEY).unwrap(),
            "invalid_input"
        );
    }

    #[test]
    fn rest_errors_answer_json_with_the_kind() {
        let response = ErrorReply(ServiceError::NotFound("no clip \"x\"".into())).into_response();
        assert_eq!(response.status(), StatusCode::NOT_FOUND);
        assert!(response.headers().get(header::RETRY_AFTER).is_none());
        let response = ErrorReply(ServiceError::NotReady).into_response();
        assert_eq!(response.status(), StatusCode::SERVICE_UNAVAILABLE);
        assert_eq!(response.headers().get(header::RETRY_AFTER).unwrap(), "1");
    }

    #[test]
    fn a_full_disk_is_insufficient_storage_and_other_file_failures_are_internal() {
        let full = std::io::Error::from(std::io::ErrorKind::StorageFull);
        let error = ServiceError::storage("cannot store clip abc", &full);
        assert_eq!(error.kind(), ServiceErrorKind::InsufficientStorage);
        assert!(error.to_string().contains("disk is full"), "{error}");
        let response = ErrorReply(error).into_response();
        assert_eq!(response.status(), StatusCode::INSUFFICIENT_STORAGE);
        assert!(response.headers().get(header::RETRY_AFTER).is_none());
        let refusal = status(ServiceError::storage("x", &full));
        assert_eq!(refusal.code(), Code::ResourceExhausted);
        assert_eq!(
            refusal.metadata().get(GRPC_KIND_KEY).unwrap(),
            "insufficient_storage"
        );
        let denied = std::io::Error::from(std::io::ErrorKind::PermissionDenied);
        assert_eq!(
            ServiceError::storage("cannot store clip abc", &denied).kind(),
            ServiceErrorKind::Internal
        );
    }

    #[test]
    fn engine_and_renderer_errors_are_classified_by_who_can_fix_them() {
        use c4g_engine::EngineError;
        use c4g_scene::SceneError;
        let cases = [
            (
                ServiceError::from(EngineError::InvalidInput("x".into())),
                ServiceErrorKind::InvalidInput,
            ),
            (
                ServiceError::from(EngineError::NoFeatureDecoder {
                    package: "p".into(),
                }),
                ServiceErrorKind::Unsupported,
            ),
            (
                ServiceError::from(EngineError::ModelOutput("x".into())),
                ServiceErrorKind::Internal,
            ),
            (
                ServiceError::from(SceneError::InvalidCamera("x".into())),
                ServiceErrorKind::InvalidInput,
            ),
            (
                ServiceError::from(SceneError::Gpu("lost".into())),
                ServiceErrorKind::Internal,
            ),
        ];
        for (error, kind) in cases {
            assert_eq!(error.kind(), kind, "{error}");
        }
    }
}
