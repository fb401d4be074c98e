//! The one error type of this crate.
//!
//! Everything that can go wrong when building or checking scene data is a variant here, so a
//! caller (the engine, the server) maps one type to its own errors in one place.

use thiserror::Error;

/// Why a piece of scene data was rejected.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum RendererError {
    /// A packed canonical buffer whose length is not a multiple of 14.
    #[error("a canonical Gaussian buffer holds a multiple of {channels} floats, got {len}")]
    CanonicalLength {
        /// Floats found.
        len: usize,
        /// Floats per Gaussian.
        channels: usize,
    },
    /// The arrays of a Gaussian set (or its feature block) disagree on the number of Gaussians.
    #[error("{field} holds {actual} entries, expected {expected} (one per Gaussian)")]
    LengthMismatch {
        /// Which array.
        field: &'static str,
        /// Entries expected.
        expected: usize,
        /// Entries found.
        actual: usize,
    },
    /// A feature block of width zero.
    #[error("a feature block must be at least one value wide")]
    ZeroFeatureWidth,
    /// One Gaussian breaks an invariant of the canonical layout.
    #[error("Gaussian {index}: {reason}")]
    InvalidGaussian {
        /// Index of the first offending Gaussian.
        index: usize,
        /// The invariant it breaks.
        reason: String,
    },
    /// Camera parameters that cannot describe a pinhole camera.
    #[error("invalid camera: {0}")]
    InvalidCamera(String),
}
