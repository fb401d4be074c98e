//! The scene vocabulary of the C4G service.
//!
//! What a decoded moment of a clip *is* ([`GaussianSet`]) and what looks at it ([`Camera`]).
//! The engine produces Gaussian sets; the rasterizers (a later addition) consume them together
//! with cameras. Nothing here knows about models, ONNX or networks.

mod camera;
mod error;
mod gaussians;

pub use camera::{Camera, Intrinsics, NormalizedIntrinsics};
pub use error::RendererError;
pub use gaussians::{CANONICAL_CHANNELS, FeatureBlock, Gaussian, GaussianSet};
