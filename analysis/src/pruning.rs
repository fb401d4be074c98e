//! Model only what a scene requires: which Gaussians of a clip change nothing that can be seen,
//! and which do not move.
//!
//! C4G decodes a fixed number of Gaussians (2,048 for the official model) whatever the scene, and
//! many end up invisible (opacity near zero at every time) or hidden (behind others, outside every
//! view). [`SceneAnalysis::measure`] samples a clip's sets at some times and renders each from some
//! cameras (the context camera and a ring of nearby novel views, say), recording per Gaussian:
//! - its largest opacity over the times;
//! - its largest **contribution** over the renders: its blending weights summed over the pixels,
//!   Σ transmittance · alpha, in pixels
//!   ([`CpuRasterizer::render_with_contributions`]);
//! - its **motion**: the largest distance of its centre from where it is at the first time.
//!
//! Why contribution is the right measure: with colours and background in [0, 1], removing one
//! Gaussian changes no pixel by more than its blending weight there (what it added, at most its
//! weight, minus what it hid behind it, at most the same), so a Gaussian's contribution bounds the
//! change its removal makes to a render's sum of absolute differences, per channel. Dropping
//! several adds their bounds (to first order: each removal lets a little more light through to
//! the others). The bound holds for the views measured; views far from them are not covered.
//!
//! What [`SceneAnalysis::keep`] drops is then exact for renders from those views within the
//! stated tolerance. The static/moving split ([`SceneAnalysis::moving`]) is for keyframing and
//! streaming: a static Gaussian is sent, or interpolated, once.

use c4g_renderer::raster::{CpuRasterizer, RenderOptions};
use c4g_scene::{Camera, GaussianSet, SceneError};

/// What counts as negligible.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PruneOptions {
    /// A Gaussian whose opacity stays below this at every sampled time is invisible: every pixel
    /// would skip it (the forward model skips alpha below 1/255, the default).
    pub opacity_floor: f32,
    /// A Gaussian whose contribution stays below this many pixels in every render is dropped.
    /// Half a pixel by default: a removal then changes a render's summed absolute difference by
    /// less than half a pixel's full colour.
    pub contribution_floor: f32,
}

impl Default for PruneOptions {
    fn default() -> Self {
        Self {
            opacity_floor: c4g_renderer::raster::ALPHA_MIN,
            contribution_floor: 0.5,
        }
    }
}

/// Per Gaussian, what the sampled times and views show of it.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct SceneAnalysis {
    /// Largest opacity over the sampled times.
    pub max_opacity: Vec<f32>,
    /// Largest contribution over the renders, in pixels.
    pub max_contribution: Vec<f32>,
    /// Largest distance of the centre from its position at the first sampled time, scene units.
    pub motion: Vec<f32>,
    /// Renders measured (times × cameras).
    pub renders: usize,
}

impl SceneAnalysis {
    /// Renders every set from every camera and records what each Gaussian shows.
    ///
    /// The sets are one clip's at several times: the same Gaussians, so of one length. Fails when
    /// they are not, or when there are no sets or no cameras, or when a render fails.
    pub fn measure(
        sets: &[GaussianSet],
        cameras: &[Camera],
        rasterizer: &CpuRasterizer,
        options: &RenderOptions,
    ) -> Result<Self, SceneError> {
        let invalid = |reason: String| Err(SceneError::InvalidRenderOptions(reason));
        let Some(first) = sets.first() else {
            return invalid("a scene analysis needs at least one set".into());
        };
        if cameras.is_empty() {
            return invalid("a scene analysis needs at least one camera".into());
        }
        let n = first.len();
        if let Some(other) = sets.iter().find(|s| s.len() != n) {
            return invalid(format!(
                "the sets of one clip hold the same Gaussians: {n} and {}",
                other.len()
            ));
        }
        let mut analysis = Self {
            max_opacity: vec![0.0; n],
            max_contribution: vec![0.0; n],
            motion: vec![0.0; n],
            renders: 0,
        };
        for set in sets {
            for (max, &opacity) in analysis.max_opacity.iter_mut().zip(set.opacities()) {
                *max = max.max(opacity);
            }
            for ((motion, p), p0) in analysis
                .motion
                .iter_mut()
                .zip(set.positions())
                .zip(first.positions())
            {
                let d = (0..3).map(|k| (p[k] - p0[k]).powi(2)).sum::<f32>().sqrt();
                *motion = motion.max(d);
            }
            for camera in cameras {
                let (_, contributions) =
                    rasterizer.render_with_contributions(set, camera, options)?;
                for (max, c) in analysis.max_contribution.iter_mut().zip(contributions) {
                    *max = max.max(c);
                }
                analysis.renders += 1;
            }
        }
        Ok(analysis)
    }

    /// Gaussians to keep: visible at some time and contributing in some view.
    pub fn keep(&self, options: &PruneOptions) -> Vec<bool> {
        self.max_opacity
            .iter()
            .zip(&self.max_contribution)
            .map(|(&o, &c)| o >= options.opacity_floor && c >= options.contribution_floor)
            .collect()
    }

    /// The bound, in pixels, on how much dropping what [`keep`](Self::keep) drops changes any
    /// one measured render's summed absolute difference per channel: the dropped contributions'
    /// sum (each at its largest over the renders), to first order.
    pub fn dropped_contribution(&self, options: &PruneOptions) -> f32 {
        self.keep(options)
            .iter()
            .zip(&self.max_contribution)
            .filter(|(k, _)| !**k)
            .map(|(_, c)| c)
            .sum()
    }

    /// Gaussians whose centre moves more than `tolerance` (scene units) over the sampled times.
    pub fn moving(&self, tolerance: f32) -> Vec<bool> {
        self.motion.iter().map(|&m| m > tolerance).collect()
    }
}
