//! What can go wrong loading and running ONNX graphs, and the coarse kind every model crate
//! reports.
//!
//! [`RuntimeError`] is the part of `c4g-engine`'s and `c4g-refiner`'s errors that comes from ONNX
//! Runtime; each crate wraps it whole (`EngineError::Runtime`, `RefinerError::Runtime`), so its
//! messages are theirs. [`ErrorKind`] is one enum for both crates: the server maps it to HTTP
//! statuses and gRPC codes, the refiner's worker reports it with a failed job and retries on it.

use std::path::PathBuf;

use thiserror::Error;

/// What went wrong, grouped by who can fix it: the kind every c4g model crate's errors report.
///
/// Both model crates map onto the same kinds. For the refiner that decided two cases: a LoRA that
/// cannot be read or applied is [`Package`](Self::Package) (the LoRA is part of what the operator
/// deployed, next to the package), and an execution provider that is unavailable is
/// [`Unsupported`](Self::Unsupported), as in the engine. The latter happens only when sessions
/// are created, at load, so the worker's retry rule (a job failed with `Runtime` or `ModelOutput`
/// goes back to the queue) sees no difference.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum ErrorKind {
    /// The request itself is wrong (bad times, wrong shapes or frame counts, an undecodable image):
    /// the caller fixes it.
    InvalidInput,
    /// The request is well-formed but this package or build cannot serve it (no feature decoder,
    /// an execution provider not compiled in or not offered by the ONNX Runtime installed).
    Unsupported,
    /// What the operator deployed is missing or malformed: the model package, or a LoRA that
    /// cannot be applied to it. The operator fixes it.
    Package,
    /// ONNX Runtime could not be loaded or failed while running: the operator fixes it.
    Runtime,
    /// A graph produced something that breaks the output contract.
    ModelOutput,
    /// The caller stopped the run (the refiner's progress callback): nothing to fix.
    Cancelled,
}

/// Every failure of loading ONNX Runtime, creating sessions and running graphs.
#[derive(Debug, Error)]
pub enum RuntimeError {
    /// `ORT_DYLIB_PATH` is not set and no library path was given.
    #[error(
        "ONNX Runtime is not configured: set ORT_DYLIB_PATH to libonnxruntime.so (from the onnxruntime PyPI wheel, under onnxruntime/capi/)"
    )]
    NotConfigured,
    /// The ONNX Runtime library could not be loaded.
    #[error("cannot load ONNX Runtime from {path}: {reason}")]
    Load {
        /// The library path tried.
        path: PathBuf,
        /// Why.
        reason: String,
    },
    /// An ONNX Runtime call failed (session creation, run, tensor creation or extraction).
    #[error("ONNX Runtime failed while {context}: {source}")]
    Ort {
        /// What the caller was doing.
        context: String,
        /// ONNX Runtime's error.
        source: ort::Error,
    },
    /// An execution provider this build or this ONNX Runtime cannot offer.
    #[error("execution provider {provider} is unavailable: {reason}")]
    ExecutionProviderUnavailable {
        /// The provider asked for.
        provider: String,
        /// Why it cannot be used.
        reason: String,
    },
    /// A graph's output is missing or not of the shape its caller expects; the message names the
    /// graph and the output.
    #[error("the model produced invalid output: {0}")]
    ModelOutput(String),
}

impl RuntimeError {
    /// Who can fix it.
    pub fn kind(&self) -> ErrorKind {
        match self {
            Self::NotConfigured | Self::Load { .. } | Self::Ort { .. } => ErrorKind::Runtime,
            Self::ExecutionProviderUnavailable { .. } => ErrorKind::Unsupported,
            Self::ModelOutput(_) => ErrorKind::ModelOutput,
        }
    }

    /// A `map_err` adapter for ONNX Runtime errors, with what the caller was doing.
    pub fn ort<E: Into<ort::Error>>(context: impl Into<String>) -> impl FnOnce(E) -> Self {
        let context = context.into();
        move |source| Self::Ort {
            context,
            source: source.into(),
        }
    }
}

/// Result with this crate's error.
pub type Result<T, E = RuntimeError> = std::result::Result<T, E>;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn each_error_has_the_kind_of_who_fixes_it() {
        let load = RuntimeError::Load {
            path: "/x/libonnxruntime.so".into(),
            reason: "missing".into(),
        };
        let provider = RuntimeError::ExecutionProviderUnavailable {
            provider: "CUDA (device 0)".into(),
            reason: "not built".into(),
        };
        let output = RuntimeError::ModelOutput("the decoder returned no \"gaussians\"".into());
        assert_eq!(RuntimeError::NotConfigured.kind(), ErrorKind::Runtime);
        assert_eq!(load.kind(), ErrorKind::Runtime);
        assert_eq!(provider.kind(), ErrorKind::Unsupported);
        assert_eq!(output.kind(), ErrorKind::ModelOutput);
        assert_eq!(
            output.to_string(),
            "the model produced invalid output: the decoder returned no \"gaussians\""
        );
    }
}
