//! What went wrong, in the service's own words: the one error that the core (`service`, `intake`,
//! `store`, `jobs`, `refine`) returns, and the kind a client switches on.
//!
//! Nothing here knows about HTTP or gRPC: `error` turns a [`ServiceErrorKind`] into a status
//! code for each transport, in one place. Engine and renderer errors keep their own message and
//! are classified here, exhaustively: a new variant in either crate does not compile until it is
//! given a kind.

use std::time::Duration;

use c4g_engine::{EngineError, ErrorKind as EngineErrorKind};
use c4g_scene::SceneError;

/// An error answered to a client. Messages say what happened and what to do about it.
#[derive(Debug, thiserror::Error)]
pub enum ServiceError {
    /// The model is still loading.
    #[error("the model is still loading; retry shortly")]
    NotReady,
    /// The server is shutting down: it finishes what it has and takes nothing new.
    #[error("the server is shutting down; retry (another replica will answer)")]
    Draining,
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
    /// Well-formed, but this model package (or this server) cannot do it: the message says what
    /// is missing.
    #[error("{0}")]
    Unsupported(String),
    /// Every encode slot is taken.
    #[error("every encode slot is busy; retry in {}s", retry_after.as_secs())]
    Busy {
        /// When to try again.
        retry_after: Duration,
    },
    /// The queue of decode and render work is full.
    #[error("the server is overloaded; retry in {}s", retry_after.as_secs())]
    Overloaded {
        /// When to try again.
        retry_after: Duration,
    },
    /// The store's disk is full: nothing was stored (see [`storage`](Self::storage)).
    #[error("{0}")]
    InsufficientStorage(String),
    /// The client took longer than a limit allows (a request body that did not arrive in time).
    #[error("{0}")]
    TimedOut(String),
    /// A service the server depends on (the job database) failed or cannot be reached: nothing
    /// was changed, and the request may succeed when it is back.
    #[error("{0}")]
    Unavailable(String),
    /// The server failed; the message is logged and shown.
    #[error("internal error: {0}")]
    Internal(String),
    /// An engine error, classified by its kind.
    #[error(transparent)]
    Engine(#[from] EngineError),
    /// A renderer error, classified by its variant.
    #[error(transparent)]
    Renderer(#[from] SceneError),
    /// One error answered to several requests (a batched decode that failed), as it is.
    #[error(transparent)]
    Shared(std::sync::Arc<ServiceError>),
}

/// The kinds of [`ServiceError`], as clients see them: the JSON `kind` of a REST error and the
/// `c4g-error-kind` metadata entry of a gRPC one ([`name`](Self::name)).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum ServiceErrorKind {
    /// The model is still loading: retry.
    NotReady,
    /// The server is shutting down: retry, elsewhere.
    Draining,
    /// The caller's request is wrong: the caller fixes it.
    InvalidInput,
    /// No or a wrong API key.
    Unauthorized,
    /// A clip, job or frame that does not exist.
    NotFound,
    /// Over a configured limit.
    TooLarge,
    /// Media of a kind the service does not read.
    UnsupportedMedia,
    /// Media of a known kind that cannot be read.
    UnreadableMedia,
    /// Well-formed, but this model package or build cannot do it.
    Unsupported,
    /// Every encode slot is busy: retry later.
    Busy,
    /// The work queue is full: retry later.
    Overloaded,
    /// The store's disk is full: the operator frees space (or the client deletes clips).
    InsufficientStorage,
    /// The client was too slow (a request body that did not arrive in time).
    TimedOut,
    /// A service the server depends on is down: retry later; the operator restores it.
    Unavailable,
    /// The server (or its model package) failed: the operator fixes it.
    Internal,
}

impl ServiceErrorKind {
    /// Every kind, for tables and tests.
    pub const ALL: [Self; 15] = [
        Self::NotReady,
        Self::Draining,
        Self::InvalidInput,
        Self::Unauthorized,
        Self::NotFound,
        Self::TooLarge,
        Self::UnsupportedMedia,
        Self::UnreadableMedia,
        Self::Unsupported,
        Self::Busy,
        Self::Overloaded,
        Self::InsufficientStorage,
        Self::TimedOut,
        Self::Unavailable,
        Self::Internal,
    ];

    /// The stable name clients switch on.
    pub fn name(self) -> &'static str {
        match self {
            Self::NotReady => "not_ready",
            Self::Draining => "draining",
            Self::InvalidInput => "invalid_input",
            Self::Unauthorized => "unauthorized",
            Self::NotFound => "not_found",
            Self::TooLarge => "too_large",
            Self::UnsupportedMedia => "unsupported_media",
            Self::UnreadableMedia => "unreadable_media",
            Self::Unsupported => "unsupported",
            Self::Busy => "busy",
            Self::Overloaded => "overloaded",
            Self::InsufficientStorage => "insufficient_storage",
            Self::TimedOut => "timed_out",
            Self::Unavailable => "unavailable",
            Self::Internal => "internal",
        }
    }
}

impl ServiceError {
    /// Shorthand for [`ServiceError::InvalidInput`].
    pub fn invalid(message: impl Into<String>) -> Self {
        Self::InvalidInput(message.into())
    }

    /// A file operation of the store that failed: `what` says what it was for. A full disk (or
    /// quota) is [`InsufficientStorage`](Self::InsufficientStorage), the one storage failure a
    /// client should hear about as such (it is not the request's fault, and it passes when space
    /// returns); any other is the server's failure.
    pub fn storage(what: impl std::fmt::Display, error: &std::io::Error) -> Self {
        use std::io::ErrorKind;
        match error.kind() {
            ErrorKind::StorageFull | ErrorKind::QuotaExceeded | ErrorKind::FileTooLarge => {
                Self::InsufficientStorage(format!(
                    "{what}: the server's disk is full ({error}); nothing was stored. Free space on \
                     the store's disk (C4G_STORE_DIR) or delete clips, then retry"
                ))
            }
            _ => Self::Internal(format!("{what}: {error}")),
        }
    }

    /// What kind of failure this is.
    pub fn kind(&self) -> ServiceErrorKind {
        use ServiceErrorKind as K;
        match self {
            Self::NotReady => K::NotReady,
            Self::Draining => K::Draining,
            Self::InvalidInput(_) => K::InvalidInput,
            Self::Unauthorized => K::Unauthorized,
            Self::NotFound(_) => K::NotFound,
            Self::TooLarge(_) => K::TooLarge,
            Self::UnsupportedMedia(_) => K::UnsupportedMedia,
            Self::UnreadableMedia(_) => K::UnreadableMedia,
            Self::Unsupported(_) => K::Unsupported,
            Self::Busy { .. } => K::Busy,
            Self::Overloaded { .. } => K::Overloaded,
            Self::InsufficientStorage(_) => K::InsufficientStorage,
            Self::TimedOut(_) => K::TimedOut,
            Self::Unavailable(_) => K::Unavailable,
            Self::Internal(_) => K::Internal,
            Self::Engine(e) => engine_kind(e.kind()),
            Self::Renderer(e) => renderer_kind(e),
            Self::Shared(e) => e.kind(),
        }
    }

    /// When a client should try again, for the refusals that are about load, not the request.
    pub fn retry_after(&self) -> Option<Duration> {
        match self {
            Self::Busy { retry_after } | Self::Overloaded { retry_after } => Some(*retry_after),
            Self::NotReady | Self::Draining => Some(Duration::from_secs(1)),
            Self::Unavailable(_) => Some(Duration::from_secs(5)),
            Self::Shared(e) => e.retry_after(),
            _ => None,
        }
    }
}

/// The engine's "who can fix it", as the service's kinds. A cancelled engine run cannot reach
/// a client (only the refiner cancels), so it counts as the server's failure.
fn engine_kind(kind: EngineErrorKind) -> ServiceErrorKind {
    match kind {
        EngineErrorKind::InvalidInput => ServiceErrorKind::InvalidInput,
        EngineErrorKind::Unsupported => ServiceErrorKind::Unsupported,
        EngineErrorKind::Package
        | EngineErrorKind::Runtime
        | EngineErrorKind::ModelOutput
        | EngineErrorKind::Cancelled => ServiceErrorKind::Internal,
    }
}

/// Renderer errors by variant: what a request's cameras, sizes or options got wrong is the
/// caller's; a missing GPU, a thread pool or file failure, or an invalid Gaussian (which only the
/// model can have produced: sets are validated when decoded) is the server's.
fn renderer_kind(error: &SceneError) -> ServiceErrorKind {
    match error {
        SceneError::ThreadPool(_)
        | SceneError::Io { .. }
        | SceneError::GpuUnavailable(_)
        | SceneError::Gpu(_)
        | SceneError::InvalidGaussian { .. } => ServiceErrorKind::Internal,
        SceneError::CanonicalLength { .. }
        | SceneError::LengthMismatch { .. }
        | SceneError::ZeroFeatureWidth
        | SceneError::InvalidCamera(_)
        | SceneError::InvalidRenderOptions(_)
        | SceneError::InvalidTrajectory(_)
        | SceneError::InvalidImage(_)
        | SceneError::Format { .. } => ServiceErrorKind::InvalidInput,
    }
}
/// The most characters an error message quotes of what a request sent (an id, a name, a value):
/// enough to recognise it, never a request's worth of text echoed back.
pub const QUOTED_CHARS: usize = 80;

/// `text` quoted for an error message (as `{:?}` quotes it), cut to [`QUOTED_CHARS`] characters
/// with how long it was when it is longer.
pub fn quoted(text: &str) -> String {
    let count = text.chars().count();
    if count <= QUOTED_CHARS {
        return format!("{text:?}");
    }
    let head: String = text.chars().take(QUOTED_CHARS).collect();
    format!("{head:?}… ({count} characters)")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn what_a_request_sent_is_quoted_whole_when_short_and_cut_when_long() {
        assert_eq!(quoted("abc"), "\"abc\"");
        let longest = "x".repeat(QUOTED_CHARS);
        assert_eq!(quoted(&longest), format!("{longest:?}"));
        let long = "é".repeat(10_000);
        let shown = quoted(&long);
        let head = "é".repeat(QUOTED_CHARS);
        assert!(shown.starts_with(&format!("{head:?}")), "{shown}");
        assert!(shown.ends_with("… (10000 characters)"), "{shown}");
        assert!(shown.chars().count() < QUOTED_CHARS + 40);
    }
}
