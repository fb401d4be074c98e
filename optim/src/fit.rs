//! Fitting a Gaussian set to one image: render, compare, differentiate, step, now and then
//! densify. The loop that `examples/fit_image.rs` runs and the tests check learns, put together
//! from the rest of the crate; small on purpose (one camera, one target, colour loss only).

use c4g_renderer::fidelity::psnr;
use c4g_renderer::{
    BackwardOptions, CpuRasterizer, DifferentiableRasterizer, RenderGradients, RenderOptions,
};
use c4g_scene::{Camera, GaussianSet, SceneError};

use crate::adam::{Adam, AdamConfig};
use crate::densify::{DensifyConfig, DensifyReport, DensifyStats, densify};
use crate::loss::l1_dssim;
use crate::params::Params;
use crate::schedule::LearningRates;

/// When densification runs.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DensifySchedule {
    /// What it does.
    pub config: DensifyConfig,
    /// First step it runs at.
    pub from: u64,
    /// Last step it may run at.
    pub until: u64,
    /// Steps between runs.
    pub every: u64,
}

/// How to fit.
#[derive(Debug, Clone, PartialEq)]
pub struct FitConfig {
    /// The weight λ of D-SSIM in `(1 − λ)·L1 + λ·D-SSIM` (0: L1 alone, cheaper).
    pub lambda_dssim: f64,
    /// Learning rates per group over steps.
    pub rates: LearningRates,
    /// Adam's constants.
    pub adam: AdamConfig,
    /// Clip the gradient's norm to this, if set.
    pub clip_norm: Option<f64>,
    /// Densification, if any.
    pub densify: Option<DensifySchedule>,
    /// The scene's size (3DGS's `spatial_lr_scale`, and densification's clone/split boundary).
    pub extent: f64,
    /// What the render varies (the background, the footprint).
    pub render: RenderOptions,
}

/// What one step measured (of the render before the step).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StepReport {
    /// The step's index (from 0).
    pub step: u64,
    /// The loss.
    pub loss: f64,
    /// PSNR of the render against the target, dB.
    pub psnr: f64,
    /// Gaussians rendered.
    pub gaussians: usize,
    /// Densification done after the step, if it ran.
    pub densified: Option<DensifyReport>,
}

/// A fit in progress.
pub struct ImageFit {
    /// The parameters being fitted.
    pub params: Params,
    /// Their optimiser.
    pub adam: Adam,
    stats: DensifyStats,
    camera: Camera,
    target: Vec<f32>,
    config: FitConfig,
    raster: CpuRasterizer,
}

impl ImageFit {
    /// Starts fitting `start` to `target` (RGB, 3 floats a pixel, the camera's size) as `camera`
    /// sees it.
    pub fn new(
        start: &GaussianSet,
        camera: Camera,
        target: Vec<f32>,
        config: FitConfig,
    ) -> Result<Self, SceneError> {
        let params = Params::from_set(start)?;
        let pixels = camera.width() as usize * camera.height() as usize;
        if target.len() != 3 * pixels {
            return Err(SceneError::InvalidImage(format!(
                "the target holds {} values, the camera sees {pixels} pixels",
                target.len()
            )));
        }
        Ok(Self {
            adam: Adam::new(config.adam, params.len()),
            stats: DensifyStats::new(params.len()),
            params,
            camera,
            target,
            config,
            raster: CpuRasterizer::new(),
        })
    }

    /// One step.
    pub fn step(&mut self) -> Result<StepReport, SceneError> {
        let step = self.adam.steps();
        let (w, h) = (self.camera.width(), self.camera.height());
        let set = self.params.to_set();
        let (image, saved) = self
            .raster
            .render_saved(&set, &self.camera, &self.config.render)?;
        let loss = l1_dssim(&image.rgb, &self.target, w, h, self.config.lambda_dssim)?;
        let grads = self.raster.backward(
            &saved,
            &RenderGradients::rgb(&loss.gradient),
            BackwardOptions::default(),
        )?;
        self.stats.accumulate(&grads.gaussians.means2d, w, h);
        let mut g = Params::from_gradients(&grads.gaussians);
        if let Some(max) = self.config.clip_norm {
            g.clip_norm(max);
        }
        self.adam
            .step(&mut self.params, &g, self.config.rates.at(step))?;
        self.params.normalize_rotations();
        let densified = match self.config.densify {
            Some(d)
                if step >= d.from
                    && step <= d.until
                    && step > 0
                    && step.is_multiple_of(d.every) =>
            {
                Some(densify(
                    &mut self.params,
                    &mut self.adam,
                    &mut self.stats,
                    &d.config,
                    self.config.extent,
                    step,
                ))
            }
            _ => None,
        };
        Ok(StepReport {
            step,
            loss: loss.value,
            psnr: psnr(&image.rgb, &self.target, w, h, None)?,
            gaussians: set.len(),
            densified,
        })
    }

    /// The set as fitted so far.
    pub fn set(&self) -> GaussianSet {
        self.params.to_set()
    }
}
