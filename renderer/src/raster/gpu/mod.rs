//! The wgpu rasterizer: the forward model of [`super`] in compute shaders, on any GPU wgpu
//! drives (Vulkan, Metal, DX12), or on the CPU through Mesa's lavapipe where there is none.
//!
//! The pipeline is the tile-based one of 3D Gaussian splatting, every step on the GPU:
//! - `project.wgsl`: one invocation per Gaussian: skip rules, EWA projection with the FOV clamp,
//!   conic, depth key and the rectangle of 16×16 tiles of its footprint (around the 3-sigma
//!   ellipse, or the 3DGS tiles);
//! - `sort.wgsl` + `scan.wgsl`: a stable 4-bit LSD radix sort of all Gaussians by depth (ties stay
//!   in index order), then per band of tile rows: tile counts, a prefix sum, one (tile, Gaussian)
//!   pair per covered tile emitted in depth order, a stable radix sort by tile alone (which keeps
//!   the depth order inside each tile) and each tile's range (`tiles.wgsl`);
//! - `blend.wgsl`: one 16×16 workgroup per tile sharing batches of 256 splats in workgroup
//!   memory, front to back, each pixel stopping at the transmittance floor and the tile when all
//!   its pixels have (the ellipse footprint cuts at 3 sigma, the 3DGS one evaluates every pixel of
//!   its tiles); colour and depth in one pass, features 4 channels a pass.
//!
//! `frame.rs` says how a frame is cut to respect the device's limits (bands of tile rows for
//! images whose state exceeds the largest storage binding, depth-ordered chunks for more pairs
//! than a buffer holds, 2D dispatch past the workgroup-count limit); `device.rs` how the adapter is
//! chosen ([`ADAPTER_ENV`]). Buffers are kept between renders and grow to powers of two, so the
//! memory a rasterizer holds is about twice what its largest frame needed.
//!
//! Agreement: f32 throughout, with the projection rescaled against overflow; on the fixture
//! scenes, in both footprints, it matches the float64 reference to ~1e-5 (the tolerances are those
//! of the CPU rasterizer: RGB, alpha, features ≤ 2e-3 absolute, depth ≤ 1e-3 relative where
//! alpha > 0.5), see `tests/gpu.rs`.

mod device;
mod frame;
mod kernels;
mod recorder;
mod sort;

use std::sync::Mutex;

pub use device::{ADAPTER_ENV, AdapterChoice, AdapterDescription};

use super::{Image, Rasterizer, RenderOptions};
use c4g_scene::{Camera, GaussianSet, SceneError};
use device::Gpu;
use kernels::Kernels;
use recorder::{Pool, Work};

/// How to set up a [`GpuRasterizer`].
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct GpuOptions {
    /// Which adapter to open.
    pub adapter: AdapterChoice,
    /// Lowers the largest buffer the rasterizer allocates below the device's limit (bytes). The
    /// frame is then cut into more bands and chunks: useful to bound memory, and how the tests
    /// exercise those paths on small scenes.
    pub max_buffer_bytes: Option<u64>,
}

impl GpuOptions {
    /// Options from the environment: the adapter from [`ADAPTER_ENV`].
    pub fn from_env() -> Self {
        Self {
            adapter: AdapterChoice::from_env(),
            max_buffer_bytes: None,
        }
    }
}

/// Renders on a GPU with wgpu compute shaders.
///
/// Creating one opens a device and compiles the kernels (do it once); each render reuses the
/// buffers of the previous one when they are large enough. Renders from several threads take
/// turns.
pub struct GpuRasterizer {
    gpu: Gpu,
    kernels: Kernels,
    pool: Mutex<Pool>,
}

impl GpuRasterizer {
    /// Opens the adapter [`ADAPTER_ENV`] names (by default the fastest one, falling back to a
    /// software adapter).
    ///
    /// Fails with [`SceneError::GpuUnavailable`] when there is no such adapter.
    pub fn new() -> Result<Self, SceneError> {
        Self::with_options(GpuOptions::from_env())
    }

    /// Opens the adapter `options` names.
    pub fn with_options(options: GpuOptions) -> Result<Self, SceneError> {
        let gpu = Gpu::open(&options.adapter, options.max_buffer_bytes)?;
        let kernels = Kernels::new(&gpu)?;
        Ok(Self {
            gpu,
            kernels,
            pool: Mutex::new(Pool::default()),
        })
    }

    /// The adapter this rasterizer runs on.
    pub fn adapter(&self) -> &AdapterDescription {
        &self.gpu.adapter
    }

    /// The largest buffer a render allocates, in bytes.
    pub fn max_buffer_bytes(&self) -> u64 {
        self.gpu.buffer_cap
    }
}

impl std::fmt::Debug for GpuRasterizer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("GpuRasterizer")
            .field("adapter", &self.gpu.adapter)
            .field("max_buffer_bytes", &self.gpu.buffer_cap)
            .finish_non_exhaustive()
    }
}

impl Rasterizer for GpuRasterizer {
    fn render(
        &self,
        gaussians: &GaussianSet,
        camera: &Camera,
        options: &RenderOptions,
    ) -> Result<Image, SceneError> {
        options.validate()?;
        // The pool only caches buffers: one left behind by a panicking render is still usable.
        let mut pool = self.pool.lock().unwrap_or_else(|e| e.into_inner());
        let result = self.gpu.scoped(|| {
            let mut work = Work::new(&self.gpu, &self.kernels, &mut pool);
            frame::render(&mut work, gaussians, camera, options)
        });
        if result.is_err() {
            pool.clear();
        }
        result
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_rasterizer_can_be_shared_between_threads() {
        fn shareable<T: Send + Sync>() {}
        shareable::<GpuRasterizer>();
    }
}
