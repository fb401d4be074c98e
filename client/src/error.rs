//! The library's one error type.
//!
//! An answer the server gave (a REST error body or a gRPC status) is kept whole, status, `kind`
//! and message, because the `kind` is what a caller switches on (`busy` → retry later,
//! `not_found` → the clip is gone) and the message is what a person needs to read. Failures that
//! never reached an answer (connection, file, malformed payload) are separate variants.

use std::path::PathBuf;

/// Everything that can go wrong talking to a c4g server.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum Error {
    /// The server answered a REST request with an error status.
    #[error("{status} {kind}: {message}")]
    Api {
        /// HTTP status code (400, 404, 429, ...).
        status: u16,
        /// The machine-readable `kind` of the error body (`not_found`, `busy`, ...); when the body
        /// was not the API's JSON, the status's reason in snake case.
        kind: String,
        /// The server's explanation (the body's `error`).
        message: String,
        /// Seconds the server asked to wait before retrying (`Retry-After`), when it said.
        retry_after: Option<u64>,
    },
    /// The server answered a gRPC call with a non-OK status.
    #[error("grpc {}: {message}", code_name(*.code))]
    Grpc {
        /// The gRPC status code.
        code: tonic::Code,
        /// The status message.
        message: String,
    },
    /// A REST request failed before an answer arrived (connection refused, reset, timeout...).
    #[error("request to the server failed")]
    Http(#[from] reqwest::Error),
    /// The gRPC connection could not be made.
    #[error("gRPC connection to the server failed")]
    Transport(#[from] tonic::transport::Error),
    /// A local file or directory could not be read.
    #[error("cannot read {}", path.display())]
    Io {
        /// The file or directory.
        path: PathBuf,
        /// What the operating system said.
        #[source]
        source: std::io::Error,
    },
    /// The base URL is unusable.
    #[error("invalid server URL {url:?}: {reason}")]
    InvalidUrl {
        /// The URL as given.
        url: String,
        /// What is wrong with it.
        reason: String,
    },
    /// An argument was rejected before anything was sent (an API key that cannot be a header,
    /// a directory without images, ...).
    #[error("{0}")]
    InvalidInput(String),
    /// A stream of updates ended before what it follows did: the connection closed early (a
    /// server restart, a proxy's timeout). Following again may pick up where it stopped.
    #[error("{0}")]
    Interrupted(String),
    /// The server's answer does not follow the API (a truncated payload, a bad header, JSON of
    /// another shape).
    #[error("malformed answer from the server: {0}")]
    Malformed(String),
}

impl Error {
    /// The HTTP status of a REST error answer.
    pub fn status(&self) -> Option<u16> {
        match self {
            Error::Api { status, .. } => Some(*status),
            _ => None,
        }
    }

    /// The error's machine-readable kind: the REST body's `kind`, or the gRPC code in snake case
    /// (`not_found`, `invalid_argument`, ...).
    pub fn kind(&self) -> Option<&str> {
        match self {
            Error::Api { kind, .. } => Some(kind),
            Error::Grpc { code, .. } => Some(code_name(*code)),
            _ => None,
        }
    }
}

impl From<tonic::Status> for Error {
    fn from(status: tonic::Status) -> Self {
        Error::Grpc {
            code: status.code(),
            message: status.message().to_owned(),
        }
    }
}

/// The gRPC code as the spec's constant names it, in snake case, to read like a REST `kind`.
fn code_name(code: tonic::Code) -> &'static str {
    use tonic::Code;
    match code {
        Code::Ok => "ok",
        Code::Cancelled => "cancelled",
        Code::Unknown => "unknown",
        Code::InvalidArgument => "invalid_argument",
        Code::DeadlineExceeded => "deadline_exceeded",
        Code::NotFound => "not_found",
        Code::AlreadyExists => "already_exists",
        Code::PermissionDenied => "permission_denied",
        Code::ResourceExhausted => "resource_exhausted",
        Code::FailedPrecondition => "failed_precondition",
        Code::Aborted => "aborted",
        Code::OutOfRange => "out_of_range",
        Code::Unimplemented => "unimplemented",
        Code::Internal => "internal",
        Code::Unavailable => "unavailable",
        Code::DataLoss => "data_loss",
        Code::Unauthenticated => "unauthenticated",
    }
}
