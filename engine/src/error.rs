//! The one error type of this crate.
//!
//! The server maps each error's [`ErrorKind`] (shared with `c4g-refiner`, from `c4g-runtime`) to
//! HTTP statuses and gRPC codes in one place; the message of each variant is written for the
//! person who sent the request or deployed the package. Failures of ONNX Runtime itself (loading
//! it, creating sessions, runs, an output off its contract) are a [`RuntimeError`], whole.

use std::path::PathBuf;

use c4g_runtime::{ErrorKind, RuntimeError};
use thiserror::Error;

/// Every failure of the engine.
#[derive(Debug, Error)]
pub enum EngineError {
    /// Reading a package file failed.
    #[error("cannot read {path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// Why.
        source: std::io::Error,
    },
    /// `model.json` is not valid JSON of the expected shape.
    #[error("{path} is not a valid c4g package manifest: {source}")]
    Manifest {
        /// The manifest.
        path: PathBuf,
        /// The parse error, with line and column.
        source: serde_json::Error,
    },
    /// The package parses but breaks the package contract (docs/package.md).
    #[error("invalid package {dir}: {reason}")]
    InvalidPackage {
        /// The package directory.
        dir: PathBuf,
        /// Which rule it breaks.
        reason: String,
    },
    /// Loading ONNX Runtime, creating a session or running a graph failed, or a graph's output
    /// breaks its contract.
    #[error(transparent)]
    Runtime(#[from] RuntimeError),
    /// No context times to normalise against.
    #[error("no context times: at least one context frame is needed")]
    EmptyContext,
    /// A time that is NaN or infinite.
    #[error("{what} time {value} is not a finite number")]
    NonFiniteTime {
        /// "context" or "target".
        what: &'static str,
        /// The offending value.
        value: f64,
    },
    /// A target outside the span of the context times.
    #[error(
        "target time {target} is outside the context span [{first}, {last}]: the model interpolates between context frames and cannot extrapolate"
    )]
    TargetOutsideContext {
        /// The target asked for.
        target: f64,
        /// The earliest context time.
        first: f64,
        /// The latest context time.
        last: f64,
    },
    /// Normalising produced a value that is not finite (for example a span that overflows).
    #[error(
        "normalising times over the context span [{first}, {last}] does not give finite values; rescale the timestamps"
    )]
    TimeOverflow {
        /// The earliest context time.
        first: f64,
        /// The latest context time.
        last: f64,
    },
    /// A tensor or array whose shape does not match what the package declares.
    #[error("{what} has shape {actual}, expected {expected}")]
    Shape {
        /// Which tensor.
        what: String,
        /// The shape expected, e.g. "[T, 3, 224, 224]".
        expected: String,
        /// The shape found.
        actual: String,
    },
    /// An input that cannot be used for another reason (empty request, non-finite pixels, …).
    #[error("invalid input: {0}")]
    InvalidInput(String),
    /// An image that cannot be decoded or resized.
    #[error("image: {0}")]
    Image(String),
    /// Feature lifting asked of a package that has no feature decoder.
    #[error(
        "package {package} has no feature decoder (feature_decoder.onnx); feature lifting is unavailable"
    )]
    NoFeatureDecoder {
        /// The package name.
        package: String,
    },
    /// A query subset asked of a package whose decoder decodes all its queries only.
    #[error(
        "package {package}'s decoder has no query_indices input (model.json: decoder_query_subset); it cannot drop queries: export it again with `python -m c4g.package.export`"
    )]
    NoQuerySubset {
        /// The package name.
        package: String,
    },
    /// The model produced output that breaks the package contract.
    #[error("the model produced invalid output: {0}")]
    ModelOutput(String),
}

impl EngineError {
    /// The coarse kind a caller maps to a status code.
    pub fn kind(&self) -> ErrorKind {
        match self {
            Self::Io { .. } | Self::Manifest { .. } | Self::InvalidPackage { .. } => {
                ErrorKind::Package
            }
            Self::Runtime(e) => e.kind(),
            Self::NoFeatureDecoder { .. } | Self::NoQuerySubset { .. } => ErrorKind::Unsupported,
            Self::EmptyContext
            | Self::NonFiniteTime { .. }
            | Self::TargetOutsideContext { .. }
            | Self::TimeOverflow { .. }
            | Self::Shape { .. }
            | Self::InvalidInput(_)
            | Self::Image(_) => ErrorKind::InvalidInput,
            Self::ModelOutput(_) => ErrorKind::ModelOutput,
        }
    }

    pub(crate) fn shape(what: impl Into<String>, expected: &[ShapeDim], actual: &[usize]) -> Self {
        Self::Shape {
            what: what.into(),
            expected: format_dims(expected),
            actual: format!("{actual:?}"),
        }
    }
}

/// One dimension of an expected shape, for error messages: a named free axis or a fixed size.
#[derive(Debug, Clone, Copy)]
pub(crate) enum ShapeDim {
    Free(&'static str),
    Fixed(usize),
}

pub(crate) fn format_dims(dims: &[ShapeDim]) -> String {
    let parts: Vec<String> = dims
        .iter()
        .map(|d| match d {
            ShapeDim::Free(name) => (*name).to_owned(),
            ShapeDim::Fixed(n) => n.to_string(),
        })
        .collect();
    format!("[{}]", parts.join(", "))
}

/// Result with the engine's error.
pub type Result<T, E = EngineError> = std::result::Result<T, E>;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn outside_span_message_names_the_value_the_span_and_the_reason() {
        let msg = EngineError::TargetOutsideContext {
            target: 7.5,
            first: 0.0,
            last: 6.0,
        }
        .to_string();
        assert!(msg.contains("7.5") && msg.contains("[0, 6]"), "{msg}");
        assert!(msg.contains("cannot extrapolate"), "{msg}");
    }

    #[test]
    fn shape_errors_spell_out_the_expected_axes() {
        let err = EngineError::shape(
            "frames",
            &[
                ShapeDim::Free("T"),
                ShapeDim::Fixed(3),
                ShapeDim::Fixed(224),
            ],
            &[2, 4, 224],
        );
        assert_eq!(
            err.to_string(),
            "frames has shape [2, 4, 224], expected [T, 3, 224]"
        );
        assert_eq!(err.kind(), ErrorKind::InvalidInput);
    }
}
