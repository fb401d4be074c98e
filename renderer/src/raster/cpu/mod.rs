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

mod bin;
mod blend;
mod pixel;
mod project;

use std::sync::Arc;

use rayon::prelude::*;

use super::{FeatureImage, Image, Rasterizer, RenderOptions};
use bin::{Chunks, TileGrid};
use blend::{TileAcc, TileRow, blend_tile, d2_cut};
use c4g_scene::{Camera, GaussianSet, SceneError};
pub use pixel::PixelWeight;
// The 3DGS footprint's rule, for the differentiable render of `c4g_analysis::align`.
pub use project::tiles_3dgs;
use project::{Splat, View};

/// Tile edge in pixels.
pub const TILE: u32 = 16;
/// Most (tile, splat) pairs held at once; more are processed in successive bands of tiles.
pub const PAIR_BUDGET: usize = 1 << 24;

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
        let job = || render_frame(gaussians, camera, options, self.pair_budget, contributions);
        Ok(match &self.pool {
            Some(pool) => pool.install(job),
            None => job(),
        })
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

/// The whole render on the current rayon pool.
/// One render, and with `contributions` every Gaussian's blending weight summed over the image's
/// pixels (Σ transmittance · alpha; 0 for a Gaussian that reaches no pixel).
fn render_frame(
    set: &GaussianSet,
    camera: &Camera,
    options: &RenderOptions,
    pair_budget: usize,
    contributions: bool,
) -> (Image, Option<Vec<f32>>) {
    let view = View::new(camera, options);
    let mut splats: Vec<Splat> = (0..set.len())
        .into_par_iter()
        .filter_map(|i| view.project(set, i))
        .collect();
    // Depth is ≥ near > 0, so its bit pattern orders like its value.
    splats.par_sort_unstable_by_key(|s| (u64::from(s.depth.to_bits()) << 32) | u64::from(s.index));

    let features = set.features().filter(|_| options.features);
    let channels = features.map_or(0, |f| f.width());
    let grid = TileGrid::new(view.width, view.height);
    let chunks = Chunks::count(&grid, &splats);
    let mut image = Image {
        width: view.width,
        height: view.height,
        rgb: vec![0.0; grid.pixels() * 3],
        alpha: vec![0.0; grid.pixels()],
        depth: vec![0.0; grid.pixels()],
        expected_depth: vec![0.0; grid.pixels()],
        features: (channels > 0).then(|| FeatureImage {
            channels,
            values: vec![0.0; grid.pixels() * channels],
        }),
    };
    let mut rows = TileRow::split(&grid, &mut image);
    let cut = d2_cut(options.footprint);
    let mut sums = contributions.then(|| vec![0.0f32; set.len()]);
    for band in grid.bands(&chunks.totals, pair_budget) {
        let pairs = chunks.fill_band(&grid, &splats, band.clone());
        let (first, last) = (band.start / grid.tiles_x, (band.end - 1) / grid.tiles_x);
        let partial: Vec<Vec<(u32, f32)>> = rows[first..=last]
            .par_iter_mut()
            .map(|row| {
                let mut acc = TileAcc::new(channels);
                let mut local = Vec::new();
                let tiles = (row.index * grid.tiles_x).max(band.start)
                    ..((row.index + 1) * grid.tiles_x).min(band.end);
                for t in tiles {
                    let k = t - band.start;
                    acc.clear();
                    blend_tile(
                        &mut acc,
                        &grid,
                        t,
                        &pairs.splats[pairs.offsets[k]..pairs.offsets[k + 1]],
                        &splats,
                        features.map(|f| (f.width(), f.values())),
                        cut,
                        contributions.then_some(&mut local),
                    );
                    row.write(&grid, t, &acc, options.background);
                }
                local
            })
            .collect();
        if let Some(sums) = &mut sums {
            for (index, value) in partial.into_iter().flatten() {
                sums[index as usize] += value;
            }
        }
    }
    (image, sums)
}
