//! The rasterizer the service renders with: the CPU one, or wgpu's when built with the `gpu`
//! feature and asked for (or, with `auto`, when a hardware GPU is present), and the footprint it
//! renders with (the package's, unless `--footprint` says otherwise).

use c4g_renderer::{CpuRasterizer, Image, Rasterizer, RenderOptions};
use c4g_scene::Footprint;
use c4g_scene::{Camera, GaussianSet};

use crate::ServiceError;
use crate::config::RendererArg;

/// The rasterizer the service renders with.
pub struct Renderer {
    inner: Box<dyn Rasterizer + Send + Sync>,
    name: String,
    footprint: Footprint,
}

impl Renderer {
    /// The rasterizer `choice` asks for, rendering with `footprint`. `auto` takes wgpu only on a
    /// hardware GPU: on a CPU, the CPU rasterizer is faster than wgpu on Mesa's software Vulkan.
    pub fn new(choice: RendererArg, footprint: Footprint) -> Result<Self, String> {
        #[cfg(feature = "gpu")]
        {
            use c4g_renderer::GpuRasterizer;
            match (choice, GpuRasterizer::new()) {
                (RendererArg::Gpu, Ok(gpu)) => return Ok(Self::gpu(gpu, footprint)),
                (RendererArg::Gpu, Err(e)) => return Err(format!("no wgpu adapter: {e}")),
                (RendererArg::Auto, Ok(gpu)) if !gpu.adapter().software => {
                    return Ok(Self::gpu(gpu, footprint));
                }
                _ => {}
            }
        }
        #[cfg(not(feature = "gpu"))]
        if choice == RendererArg::Gpu {
            return Err("`--renderer gpu` needs c4g-server built with `--features gpu`".into());
        }
        Ok(Self {
            inner: Box::new(CpuRasterizer::new()),
            name: "cpu".into(),
            footprint,
        })
    }

    #[cfg(feature = "gpu")]
    fn gpu(gpu: c4g_renderer::GpuRasterizer, footprint: Footprint) -> Self {
        let name = format!("wgpu ({})", gpu.adapter().name);
        Self {
            inner: Box::new(gpu),
            name,
            footprint,
        }
    }

    /// Which rasterizer this is, for `/v1/models` and logs.
    pub fn name(&self) -> &str {
        &self.name
    }

    /// Which pixels each Gaussian is evaluated at.
    pub fn footprint(&self) -> Footprint {
        self.footprint
    }

    /// Renders one view.
    pub fn render(
        &self,
        set: &GaussianSet,
        camera: &Camera,
        background: [f32; 3],
    ) -> Result<Image, ServiceError> {
        self.render_with(set, camera, background, false)
    }

    /// Renders one view with the set's feature vectors composited into its feature channels.
    pub fn render_features(
        &self,
        set: &GaussianSet,
        camera: &Camera,
        background: [f32; 3],
    ) -> Result<Image, ServiceError> {
        self.render_with(set, camera, background, true)
    }

    fn render_with(
        &self,
        set: &GaussianSet,
        camera: &Camera,
        background: [f32; 3],
        features: bool,
    ) -> Result<Image, ServiceError> {
        let options = RenderOptions {
            background,
            features,
            footprint: self.footprint,
            ..RenderOptions::default()
        };
        Ok(self.inner.render(set, camera, &options)?)
    }
}
