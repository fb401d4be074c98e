//! Rasterization: Gaussian sets seen by a camera become images.
//!
//! Every rasterizer implements the same forward model (3D Gaussian splatting with the constants
//! below, the 3DGS / gsplat convention of C4G_MODEL.md), so they are interchangeable and each
//! is a check on the others:
//! - a Gaussian is skipped when any parameter is non-finite (its feature vector included, when the
//!   set has one, whether or not features are rendered), its rotation has zero norm, or its
//!   camera-space depth z lies outside `[near, far]`; rotations need not be unit (they are
//!   normalised), scales may be zero;
//! - EWA projection: `J = [[fx/z, 0, -fx·x/z²], [0, fy/z, -fy·y/z²]]` with x/z and y/z clamped to
//!   ±[`FOV_CLAMP`] × the half-FOV tangent (`W / 2fx`, `H / 2fy`); `Σ2D = J W Σ Wᵀ Jᵀ + EPS2D·I`,
//!   `W` the rotation of the world-to-camera pose, `Σ = R S Sᵀ Rᵀ`;
//! - the mean projects to `u = fx·x/z + cx`, `v = fy·y/z + cy`; pixel `(i, j)` is evaluated at its
//!   centre `(i + 0.5, j + 0.5)`;
//! - a Gaussian reaches a pixel when the Mahalanobis distance `d` of the pixel centre under `Σ2D`
//!   is at most [`SIGMA_EXTENT`]; there `alpha = min(ALPHA_MAX, opacity · exp(-d²/2))`, and
//!   `alpha < ALPHA_MIN` contributes nothing;
//! - front to back by camera-space depth (ties by index); a pixel stops before the Gaussian that
//!   would bring its transmittance `T` below [`TRANSMITTANCE_MIN`];
//! - outputs: colour `Σ cᵢ αᵢ Tᵢ + T·background`, alpha `1 - T`, depth `Σ zᵢ αᵢ Tᵢ`
//!   (alpha-weighted), expected depth `depth / alpha` (0 where alpha is 0), and any per-Gaussian
//!   feature channels composited like colour (no background).
//!
//! The float64 reference of the same model is `models/python/c4g/raster_reference.py`.

mod cpu;
#[cfg(feature = "gpu")]
pub mod gpu;

pub use cpu::{CpuRasterizer, PAIR_BUDGET, TILE};

use crate::{Camera, GaussianSet, RendererError};

/// Nearest camera-space depth rendered (gsplat's near plane; C4G's reference renders with it).
pub const NEAR: f32 = 0.01;
/// Farthest camera-space depth rendered.
pub const FAR: f32 = 100.0;
/// Added to the diagonal of every projected covariance: a pixel-sized low-pass filter.
pub const EPS2D: f32 = 0.3;
/// x/z and y/z are clamped to this multiple of the half-FOV tangent in the Jacobian, so Gaussians
/// far outside the view do not get absurd footprints.
pub const FOV_CLAMP: f32 = 1.3;
/// A Gaussian reaches pixels within this many standard deviations.
pub const SIGMA_EXTENT: f32 = 3.0;
/// Largest alpha one Gaussian contributes.
pub const ALPHA_MAX: f32 = 0.99;
/// Smallest alpha that counts.
pub const ALPHA_MIN: f32 = 1.0 / 255.0;
/// A pixel is finished when its transmittance would fall below this.
pub const TRANSMITTANCE_MIN: f32 = 1e-4;

/// What a render call may vary.
#[derive(Debug, Clone, PartialEq)]
pub struct RenderOptions {
    /// Colour behind the Gaussians, RGB.
    pub background: [f32; 3],
    /// Near plane (camera-space depth).
    pub near: f32,
    /// Far plane (camera-space depth).
    pub far: f32,
    /// Composite the set's per-Gaussian feature vectors into a feature image (when it has them).
    pub features: bool,
}

impl RenderOptions {
    /// Checks that these describe a render: `0 < near < far`, both finite, a finite background.
    pub fn validate(&self) -> Result<(), RendererError> {
        if !(self.near.is_finite()
            && self.far.is_finite()
            && 0.0 < self.near
            && self.near < self.far)
        {
            return Err(RendererError::InvalidRenderOptions(format!(
                "near {} and far {} must be finite with 0 < near < far",
                self.near, self.far
            )));
        }
        if !self.background.iter().all(|v| v.is_finite()) {
            return Err(RendererError::InvalidRenderOptions(format!(
                "background {:?} must be finite",
                self.background
            )));
        }
        Ok(())
    }
}

impl Default for RenderOptions {
    fn default() -> Self {
        Self {
            background: [0.0; 3],
            near: NEAR,
            far: FAR,
            features: true,
        }
    }
}

/// One rendered view. Every plane is row-major, `height` rows of `width` pixels.
#[derive(Debug, Clone, PartialEq)]
pub struct Image {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// RGB, 3 floats a pixel, interleaved.
    pub rgb: Vec<f32>,
    /// Accumulated opacity `1 - T`.
    pub alpha: Vec<f32>,
    /// Alpha-weighted depth `Σ zᵢ αᵢ Tᵢ`.
    pub depth: Vec<f32>,
    /// Expected depth `depth / alpha` (0 where alpha is 0).
    pub expected_depth: Vec<f32>,
    /// Feature channels per pixel, interleaved, when features were rendered.
    pub features: Option<FeatureImage>,
}

/// A feature image: `channels` floats a pixel, interleaved.
#[derive(Debug, Clone, PartialEq)]
pub struct FeatureImage {
    /// Floats per pixel.
    pub channels: usize,
    /// `height · width · channels` values.
    pub values: Vec<f32>,
}

/// Anything that renders Gaussian sets with the forward model above.
pub trait Rasterizer {
    /// Renders `gaussians` as `camera` sees them.
    fn render(
        &self,
        gaussians: &GaussianSet,
        camera: &Camera,
        options: &RenderOptions,
    ) -> Result<Image, RendererError>;
}
