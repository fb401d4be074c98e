//! What turns C4G scenes into pixels, and how close pixels are to each other.
//!
//! The rasterizers ([`raster`]: the forward model of 3D Gaussian splatting, its constants, the CPU
//! renderer and, behind `gpu`, the wgpu one) render a [`GaussianSet`](c4g_scene::GaussianSet) as a
//! [`Camera`](c4g_scene::Camera) sees it; [`fidelity`] compares the images (PSNR, SSIM). What the
//! renders are *used for* (camera alignment, tracks, feature fields, pruning) is `c4g-analysis`.

/// Image fidelity: PSNR and SSIM, optionally masked.
pub mod fidelity;
/// Rasterizers: the forward model, its constants and the CPU (and, with `gpu`, wgpu) renderers;
/// reverse-mode gradients of renders (`raster::grad`).
pub mod raster;

#[cfg(feature = "gpu")]
pub use raster::gpu::GpuRasterizer;
pub use raster::{
    BackwardOptions, CpuRasterizer, DifferentiableRasterizer, FeatureImage, GaussianGradients,
    Gradients, Image, PixelWeight, Rasterizer, RenderGradients, RenderOptions,
};
