//! The one error type of this crate, and the coarse kind a caller switches on.
//!
//! The worker reports [`ErrorKind`] back with a failed job; each variant's message is written for
//! the person who sent the request or deployed the package.

use std::path::PathBuf;

use thiserror::Error;

/// What went wrong, grouped by who can fix it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum ErrorKind {
    /// The request itself is wrong (frame count, sizes, steps): the caller fixes it.
    InvalidInput,
    /// The package on disk is missing or malformed: the operator fixes it.
    Package,
    /// The LoRA cannot be applied to this package: the operator fixes it.
    Lora,
    /// ONNX Runtime could not be loaded or failed while running: the operator fixes it.
    Runtime,
    /// A graph produced something that breaks the package contract.
    ModelOutput,
    /// The caller stopped the run through its progress callback.
    Cancelled,
}

/// Every failure of the refiner.
#[derive(Debug, Error)]
pub enum RefinerError {
    /// Reading a file failed.
    #[error("cannot read {path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// Why.
        source: std::io::Error,
    },
    /// A JSON file (`refiner.json`, `adapter_config.json`) is not of the expected shape.
    #[error("{path} is not valid: {source}")]
    Json {
        /// The file.
        path: PathBuf,
        /// The parse error, with line and column.
        source: serde_json::Error,
    },
    /// The package parses but breaks the package contract.
    #[error("invalid refiner package {dir}: {reason}")]
    InvalidPackage {
        /// The package directory.
        dir: PathBuf,
        /// Which rule it breaks.
        reason: String,
    },
    /// An ONNX file whose protobuf or initializer data cannot be read.
    #[error("cannot read the weights of {path}: {reason}")]
    Onnx {
        /// The `.onnx` file.
        path: PathBuf,
        /// What is wrong.
        reason: String,
    },
    /// A LoRA file that cannot be read or applied; `key` names the offending tensor when there is one.
    #[error("LoRA {path}: {reason}")]
    Lora {
        /// The LoRA file.
        path: PathBuf,
        /// What is wrong, naming the key.
        reason: String,
    },
    /// `ORT_DYLIB_PATH` is not set and no library path was given.
    #[error(
        "ONNX Runtime is not configured: set ORT_DYLIB_PATH to libonnxruntime.so (from the onnxruntime PyPI wheel, under onnxruntime/capi/)"
    )]
    RuntimeNotConfigured,
    /// The ONNX Runtime library could not be loaded.
    #[error("cannot load ONNX Runtime from {path}: {reason}")]
    RuntimeLoad {
        /// The library path tried.
        path: PathBuf,
        /// Why.
        reason: String,
    },
    /// An ONNX Runtime call failed (session creation, run, tensor extraction).
    #[error("ONNX Runtime failed while {context}: {source}")]
    Ort {
        /// What the refiner was doing.
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
    /// A request that does not fit the package or makes no sense.
    #[error("invalid refine request: {0}")]
    InvalidRequest(String),
    /// A graph returned a tensor of the wrong name, type or shape.
    #[error("model output: {0}")]
    ModelOutput(String),
    /// The progress callback asked to stop; `completed` steps had run.
    #[error("cancelled after {completed} of {total} steps")]
    Cancelled {
        /// Steps finished before stopping.
        completed: usize,
        /// Steps asked for.
        total: usize,
    },
}

/// The refiner's result type.
pub type Result<T, E = RefinerError> = std::result::Result<T, E>;

impl RefinerError {
    /// Who can fix it.
    pub fn kind(&self) -> ErrorKind {
        match self {
            Self::Io { .. }
            | Self::Json { .. }
            | Self::InvalidPackage { .. }
            | Self::Onnx { .. } => ErrorKind::Package,
            Self::Lora { .. } => ErrorKind::Lora,
            Self::RuntimeNotConfigured
            | Self::RuntimeLoad { .. }
            | Self::Ort { .. }
            | Self::ExecutionProviderUnavailable { .. } => ErrorKind::Runtime,
            Self::InvalidRequest(_) => ErrorKind::InvalidInput,
            Self::ModelOutput(_) => ErrorKind::ModelOutput,
            Self::Cancelled { .. } => ErrorKind::Cancelled,
        }
    }

    /// A `map_err` adapter for ONNX Runtime errors, with what the refiner was doing.
    pub(crate) fn ort<E: Into<ort::Error>>(context: impl Into<String>) -> impl FnOnce(E) -> Self {
        let context = context.into();
        move |source| Self::Ort {
            context,
            source: source.into(),
        }
    }

    pub(crate) fn io(path: impl Into<PathBuf>) -> impl FnOnce(std::io::Error) -> Self {
        let path = path.into();
        move |source| Self::Io { path, source }
    }
}
