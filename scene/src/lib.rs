//! The scene vocabulary of the C4G service: what a decoded moment of a clip *is*
//! ([`GaussianSet`]), what looks at it ([`Camera`]), how a camera moves ([`trajectory`]) and which
//! pixels a Gaussian reaches ([`Footprint`]).
//!
//! Every other scene crate builds on these: `c4g-formats` stores them, `c4g-renderer` turns them
//! into pixels, `c4g-analysis` learns from those pixels. Nothing here knows about models, ONNX,
//! networks or rasterizers, so the engine depends on this crate alone.

/// Pinhole cameras: intrinsics, world-to-camera poses, OpenCV axes.
mod camera;
/// The one error type of the scene crates.
mod error;
/// Which pixels a Gaussian reaches: the ellipse or 3DGS's tiles.
mod footprint;
/// Gaussian sets: the canonical layout, columns, optional feature vectors.
mod gaussians;
/// The unit tests' deterministic generator, shared with the other scene crates' unit tests.
#[cfg(any(test, feature = "test-rng"))]
#[doc(hidden)]
pub mod test_rng;
/// Camera paths: interpolation and the orbit, spiral and dolly presets.
pub mod trajectory;

pub use camera::{Camera, Intrinsics, NormalizedIntrinsics};
pub use error::SceneError;
pub use footprint::Footprint;
pub use gaussians::{CANONICAL_CHANNELS, FeatureBlock, Gaussian, GaussianSet};
pub use trajectory::Trajectory;
