//! The one error type of this crate.
//!
//! The worker reports each error's [`ErrorKind`] (shared with `c4g-engine`, from `c4g-runtime`)
//! back with a failed job; each variant's message is written for the person who sent the request
//! or deployed the package. Failures of ONNX Runtime itself (loading it, creating sessions, runs,
//! an output off its contract) are a [`RuntimeError`], whole.

use std::path::PathBuf;

use c4g_runtime::{ErrorKind, RuntimeError};
use thiserror::Error;

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
    /// Loading ONNX Runtime, creating a session or running a graph failed, or a graph's output
    /// breaks its contract.
    #[error(transparent)]
    Runtime(#[from] RuntimeError),
    /// A request that does not fit the package or makes no sense.
    #[error("invalid refine request: {0}")]
    InvalidRequest(String),
    /// A refinement's result that cannot be handed back (a frame of the wrong size, PNG
    /// encoding, a refinement thread that panicked); a graph's own output off its contract is a
    /// [`RuntimeError::ModelOutput`] instead.
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
    /// Who can fix it. A LoRA that cannot be applied is [`ErrorKind::Package`]: the LoRA is part
    /// of what the operator deployed (see [`ErrorKind`]).
    pub fn kind(&self) -> ErrorKind {
        match self {
            Self::Io { .. }
            | Self::Json { .. }
            | Self::InvalidPackage { .. }
            | Self::Onnx { .. }
            | Self::Lora { .. } => ErrorKind::Package,
            Self::Runtime(e) => e.kind(),
            Self::InvalidRequest(_) => ErrorKind::InvalidInput,
            Self::ModelOutput(_) => ErrorKind::ModelOutput,
            Self::Cancelled { .. } => ErrorKind::Cancelled,
        }
    }

    pub(crate) fn io(path: impl Into<PathBuf>) -> impl FnOnce(std::io::Error) -> Self {
        let path = path.into();
        move |source| Self::Io { path, source }
    }
}
