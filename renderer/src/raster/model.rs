//! The forward model's vocabulary, shared by every rasterizer: its constants, what a render call
//! may vary ([`RenderOptions`]), what it gives ([`Image`]) and the [`Rasterizer`] trait. The rules
//! themselves are written out in the [`raster`](super) module documentation.

use c4g_scene::{Camera, Footprint, GaussianSet, SceneError};

/// Nearest camera-space depth rendered (gsplat's near plane; the one C4G's reference passes its
/// rasterizer, whose own cull is at 0.2: see the module documentation).
pub const NEAR: f32 = 0.01;
/// Farthest camera-space depth rendered.
pub const FAR: f32 = 100.0;
/// Added to the diagonal of every projected covariance: a pixel-sized low-pass filter.
pub const EPS2D: f32 = 0.3;
/// x/z and y/z are clamped to this multiple of the half-FOV tangent in the Jacobian, so Gaussians
/// far outside the view do not get absurd footprints.
pub const FOV_CLAMP: f32 = 1.3;
/// [`Footprint::Ellipse`]: a Gaussian reaches the pixels within this many standard deviations.
/// [`Footprint::Tiles3dgs`]: its radius is this many standard deviations along the major axis.
pub const SIGMA_EXTENT: f32 = 3.0;
/// [`Footprint::Tiles3dgs`]: the floor of the discriminant in the largest eigenvalue of `Σ2D`.
pub const DISCRIMINANT_FLOOR_3DGS: f32 = 0.1;
/// [`Footprint::Tiles3dgs`]: the edge of 3DGS's tiles (its `BLOCK_X`, `BLOCK_Y`), in pixels.
pub const TILE_3DGS: u32 = 16;
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
    /// Which pixels each Gaussian is evaluated at.
    pub footprint: Footprint,
}

impl RenderOptions {
    /// Checks that these describe a render: `0 < near < far`, both finite, a finite background.
    pub fn validate(&self) -> Result<(), SceneError> {
        if !(self.near.is_finite()
            && self.far.is_finite()
            && 0.0 < self.near
            && self.near < self.far)
        {
            return Err(SceneError::InvalidRenderOptions(format!(
                "near {} and far {} must be finite with 0 < near < far",
                self.near, self.far
            )));
        }
        if !self.background.iter().all(|v| v.is_finite()) {
            return Err(SceneError::InvalidRenderOptions(format!(
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
            footprint: Footprint::Ellipse,
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
    ) -> Result<Image, SceneError>;
}
