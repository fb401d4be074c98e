//! The CPU rasterizer: the forward model of [`super`] on threads, for machines without a GPU and as
//! a second implementation to hold the wgpu one against.
//!
//! Three stages, the 3DGS layout on a CPU:
//! 1. **Project** every Gaussian (in parallel, in f64: huge or tiny scales and focal lengths make
//!    f32 covariances overflow or cancel) to a `Splat`: its pixel centre, its 2D covariance in a
//!    form whose Mahalanobis distance is a sum of non-negative terms, its depth and its pixel box:
//!    for the ellipse footprint a conservative box around the pixels its exact test can reach, for
//!    the 3DGS footprint the pixels of its 3DGS tiles. Invalid ones are dropped here.
//! 2. **Bin** splats into 16×16-pixel tiles. Splats are sorted once by (depth, index); a stable
//!    counting sort by tile then leaves every tile's list in depth order without sorting tiles
//!    (chunks of splats count their pairs per tile with 2D difference arrays, then write in
//!    parallel, each at its own offsets). The (tile, splat) pairs are built for a band of
//!    consecutive tiles at a time, sized so that the pair buffer stays under [`PAIR_BUDGET`]
//!    entries: a million screen-filling Gaussians cost time, not unbounded memory.
//! 3. **Blend** each tile (tiles in parallel): per splat and row, only the pixels of the row that
//!    its ellipse can reach are visited (3 sigma for the ellipse footprint, the 1/255 contour for
//!    the 3DGS one: a pixel beyond it fails the alpha test, so skipping it is evaluating it); a
//!    pixel composites front to back and stops at the transmittance floor; a tile stops when all
//!    its pixels have.
//!
//! Per-pixel work is in f32, on pixel offsets from the splat's centre that are exact wherever the
//! splat sits in the image (its centre is stored relative to its box's corner).
//!
//! This module holds the rasterizer and the orchestration of a frame; each stage has its file:
//! `project.rs` (Gaussian → `Splat`), `bin.rs` (the tile grid, pairs per tile, bands and the
//! parallel counting sort) and `blend.rs` (a tile's front-to-back compositing and its write into
//! the image). `pixel.rs` evaluates the same model at single pixels, Gaussian by Gaussian.

mod backward;
mod bin;
mod blend;
mod frame;
mod pixel;
mod project;
mod tiling;

use std::sync::Arc;

use super::grad::{
    BackwardOptions, DifferentiableRasterizer, Gradients, RenderGradients, check_finite,
};
use super::{Image, Rasterizer, RenderOptions};
pub use backward::CpuSaved;
use c4g_scene::{Camera, GaussianSet, SceneError};
use frame::render_frame;
pub use pixel::PixelWeight;
pub use tiling::{PAIR_BUDGET, TILE};
// The 3DGS footprint's rule, for the differentiable render of `c4g_analysis::align`.
pub use project::tiles_3dgs;

/// Renders on the CPU with rayon.
#[derive(Debug, Clone)]
pub struct CpuRasterizer {
    /// `None`: rayon's global pool (all cores).
    pool: Option<Arc<rayon::ThreadPool>>,
    pair_budget: usize,
}

impl Default for CpuRasterizer {
    fn default() -> Self {
        Self {
            pool: None,
            pair_budget: PAIR_BUDGET,
        }
    }
}

impl CpuRasterizer {
    /// A rasterizer on rayon's global pool (as many threads as cores, unless `RAYON_NUM_THREADS`
    /// says otherwise).
    pub fn new() -> Self {
        Self::default()
    }

    /// Holds at most `pairs` (tile, Gaussian) pairs (4 bytes each) at once, binning bands of
    /// tiles in turn; [`PAIR_BUDGET`] by default. Changes memory and time, never the image.
    pub fn with_pair_budget(mut self, pairs: usize) -> Self {
        self.pair_budget = pairs.max(1);
        self
    }

    /// A rasterizer with its own pool of `threads` threads (0: as many as cores).
    pub fn with_threads(threads: usize) -> Result<Self, SceneError> {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .thread_name(|i| format!("c4g-raster-{i}"))
            .build()
            .map_err(|e| SceneError::ThreadPool(e.to_string()))?;
        Ok(Self {
            pool: Some(Arc::new(pool)),
            ..Self::default()
        })
    }

    /// Threads this rasterizer renders with.
    pub fn threads(&self) -> usize {
        self.pool
            .as_ref()
            .map_or_else(rayon::current_num_threads, |p| p.current_num_threads())
    }

    /// Renders, and measures what each Gaussian contributes to the image: its blending weights
    /// summed over the pixels, Σ transmittance · alpha, in pixels (a Gaussian that covers one
    /// pixel fully and in front of everything contributes 1). Removing one Gaussian changes no
    /// pixel of a render with colours and background in [0, 1] by more than its weight there, so
    /// its contribution bounds the change it makes to the image's sum of absolute differences,
    /// per channel (up to the transmittance floor's early stop). See [`c4g_analysis::pruning`].
    pub fn render_with_contributions(
        &self,
        gaussians: &GaussianSet,
        camera: &Camera,
        options: &RenderOptions,
    ) -> Result<(Image, Vec<f32>), SceneError> {
        let (image, sums) = self.run(gaussians, camera, options, true)?;
        Ok((image, sums.unwrap_or_default()))
    }

    /// Each Gaussian's blending weight (`Tᵢ · αᵢ`) at each pixel `(x, y)`, front to back, as a
    /// render with these options composites it: the weights sum to the pixel's alpha, and
    /// weight its depth.
    pub fn pixel_weights(
        &self,
        gaussians: &GaussianSet,
        camera: &Camera,
        options: &RenderOptions,
        pixels: &[(u32, u32)],
    ) -> Result<Vec<Vec<PixelWeight>>, SceneError> {
        options.validate()?;
        Ok(pixel::pixel_weights(gaussians, camera, options, pixels))
    }

    /// Runs `job` on this rasterizer's threads.
    fn install<R: Send>(&self, job: impl FnOnce() -> R + Send) -> R {
        match &self.pool {
            Some(pool) => pool.install(job),
            None => job(),
        }
    }

    fn run(
        &self,
        gaussians: &GaussianSet,
        camera: &Camera,
        options: &RenderOptions,
        contributions: bool,
    ) -> Result<(Image, Option<Vec<f32>>), SceneError> {
        options.validate()?;
        if u32::try_from(gaussians.len()).is_err() {
            return Err(SceneError::InvalidRenderOptions(format!(
                "{} Gaussians are more than one render can index",
                gaussians.len()
            )));
        }
        Ok(self
            .install(|| render_frame(gaussians, camera, options, self.pair_budget, contributions)))
    }
}

impl DifferentiableRasterizer for CpuRasterizer {
    type Saved<'a> = CpuSaved<'a>;

    fn render_saved<'a>(
        &self,
        gaussians: &'a GaussianSet,
        camera: &Camera,
        options: &RenderOptions,
    ) -> Result<(Image, CpuSaved<'a>), SceneError> {
        options.validate()?;
        if u32::try_from(gaussians.len()).is_err() {
            return Err(SceneError::InvalidRenderOptions(format!(
                "{} Gaussians are more than one render can index",
                gaussians.len()
            )));
        }
        check_finite(gaussians)?;
        Ok(self.install(|| backward::render_saved(gaussians, camera, options, self.pair_budget)))
    }

    fn backward(
        &self,
        saved: &CpuSaved<'_>,
        upstream: &RenderGradients<'_>,
        options: BackwardOptions,
    ) -> Result<Gradients, SceneError> {
        let (width, height) = saved.size();
        upstream.validate(width, height)?;
        Ok(self.install(|| backward::backward(saved, upstream, options, self.pair_budget)))
    }
}

impl Rasterizer for CpuRasterizer {
    fn render(
        &self,
        gaussians: &GaussianSet,
        camera: &Camera,
        options: &RenderOptions,
    ) -> Result<Image, SceneError> {
        Ok(self.run(gaussians, camera, options, false)?.0)
    }
}
