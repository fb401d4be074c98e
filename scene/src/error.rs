//! The one error type of this crate.
//!
//! Everything that can go wrong when building or checking scene data is a variant here, so a
//! caller (the engine, the server) maps one type to its own errors in one place.

use thiserror::Error;

/// Why a piece of scene data was rejected.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum SceneError {
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
    /// Render options that describe no valid render (near/far, background).
    #[error("invalid render options: {0}")]
    InvalidRenderOptions(String),
    /// A rasterizer's thread pool could not be started.
    #[error("cannot start the rasterizer's thread pool: {0}")]
    ThreadPool(String),
    /// Trajectory parameters that describe no camera path.
    #[error("invalid trajectory: {0}")]
    InvalidTrajectory(String),
    /// Images that cannot be compared (sizes, masks, values).
    #[error("invalid image: {0}")]
    InvalidImage(String),
    /// A scene file that does not follow its format.
    #[error("{format} file: {reason}")]
    Format {
        /// The format ("ply", "splat", "series").
        format: &'static str,
        /// What is wrong, with where when known.
        reason: String,
    },
    /// Reading or writing a file failed.
    #[error("{path}: {message}")]
    Io {
        /// The file.
        path: String,
        /// The operating system's reason.
        message: String,
    },
    /// No GPU adapter (hardware or software) that the wgpu rasterizer can use, or none matching
    /// the one asked for.
    #[error("no usable GPU adapter: {0}")]
    GpuUnavailable(String),
    /// The GPU failed a render: device creation, a validation or out-of-memory error, a lost device,
    /// a buffer that could not be read back, or a scene beyond the device's limits.
    #[error("GPU rasterizer: {0}")]
    Gpu(String),
}
