//! The scene vocabulary of the C4G service, and what turns scenes into pixels.
//!
//! What a decoded moment of a clip *is* ([`GaussianSet`]), what looks at it ([`Camera`]), how a
//! camera moves ([`trajectory`]), where a point goes ([`tracking`]), what lifted features show
//! ([`features`]), how scenes are stored ([`formats`]), how they become images ([`raster`]), how
//! images are compared ([`metrics`]), which Gaussians a scene needs ([`pruning`]) and which
//! camera saw a frame of it ([`align`]).
//! Nothing here knows about models, ONNX or networks.

/// Camera recovery by photometric alignment: a render's analytic camera Jacobian and the
/// coarse-to-fine Levenberg–Marquardt that finds the camera matching a frame, with a confidence;
/// and given cameras' translations fitted to the model's depth scale.
pub mod align;
/// Pinhole cameras: intrinsics, world-to-camera poses, OpenCV axes.
mod camera;
/// The crate's one error type.
mod error;
/// Feature fields in images: cosine similarity, selection, a fixed PCA colouring, matching.
pub mod features;
/// Files and payloads: 3DGS `.ply`, antimatter15 `.splat`, Niantic `.spz`, time series of sets
/// (a directory, a zip of frames, a fitted `.splatv`), `C4GS` frames, `C4GV` compact streams.
pub mod formats;
/// Gaussian sets: the canonical layout, columns, optional feature vectors.
mod gaussians;
/// Image quality: PSNR and SSIM, optionally masked.
pub mod metrics;
/// Model only what a scene requires: invisible, negligible and static Gaussians of a clip.
pub mod pruning;
/// Rasterizers: the forward model, its constants and the CPU (and, with `gpu`, wgpu) renderers.
pub mod raster;
/// The unit tests' deterministic generator.
#[cfg(test)]
mod test_rng;
/// Point tracks from Gaussian trajectories: a pixel's Gaussians carry its point to other times.
pub mod tracking;
/// Camera paths: interpolation and the orbit, spiral and dolly presets.
pub mod trajectory;

pub use align::{AlignOptions, Alignment, align_camera};
pub use camera::{Camera, Intrinsics, NormalizedIntrinsics};
pub use error::RendererError;
pub use gaussians::{CANONICAL_CHANNELS, FeatureBlock, Gaussian, GaussianSet};
#[cfg(feature = "gpu")]
pub use raster::gpu::GpuRasterizer;
pub use raster::{CpuRasterizer, FeatureImage, Image, PixelWeight, Rasterizer, RenderOptions};
pub use trajectory::Trajectory;
