//! Gradients of a render: the interface every differentiable rasterizer implements, and the types
//! that carry gradients in and out.
//!
//! A loss of a rendered [`Image`] hands back its gradient with respect to the image's planes
//! ([`RenderGradients`]: colour, and optionally alpha and expected depth); a
//! [`DifferentiableRasterizer`] turns that into the gradient with respect to every Gaussian
//! ([`GaussianGradients`], in the optimiser's parametrisation) and to the camera
//! ([`CameraGradients`]), in reverse mode, at a small multiple of the forward render's cost. Apart
//! from the CPU implementation (`cpu/backward.rs`) so that a wgpu one can implement the same trait
//! and be held to the same tests.
//!
//! ## Parametrisation
//! Gradients are with respect to what an optimiser stores, not the canonical set's activated
//! values: position as is; scale as `log s` (so `∂L/∂log s = s·∂L/∂s`); rotation as the stored,
//! unnormalised quaternion `q` (`w, x, y, z`), through the normalisation `q/|q|` (so the gradient
//! is orthogonal to `q`); opacity as its logit `θ`, `o = sigmoid(θ)` (so `∂L/∂θ = o(1 − o)·∂L/∂o`);
//! colour as is. The camera: a left se(3) increment of world-to-camera, `exp([ω, ν]^)·W`, and the
//! log of a scale shared by `fx` and `fy`, at zero: the seven parameters of `c4g_analysis::align`,
//! in its order `[ωx, ωy, ωz, νx, νy, νz, log focal]`.
//!
//! ## Where the forward model is not smooth (the conventions, as 3DGS defines them)
//! The render is piecewise smooth; gradients are those of the piece the forward pass took:
//! - **alpha clamp**: where `opacity·exp(−d²/2) > 0.99` alpha is the constant 0.99, so opacity and
//!   shape get no gradient from that pixel (colour and depth still do, through its weight);
//! - **1/255 skip, the footprint's edge** (3 sigma for the ellipse, the 3DGS tiles), the
//!   **FOV clamp's** choice of branch and the **pixel boxes** are held fixed: a skipped (pixel,
//!   Gaussian) pair contributes nothing to any gradient, and the motion of an edge (a jump of the
//!   image) is not differentiated;
//! - **early termination**: the Gaussian that would bring transmittance under 1e-4 and all behind
//!   it get no gradient from that pixel; the ones in front see the stopped pixel's final
//!   transmittance, exactly as the forward pass composited it;
//! - Gaussians the forward pass **skips** (behind the near plane or beyond the far one, opacity
//!   under 1/255, a zero rotation, a covariance that is not positive definite) get exactly zero;
//!   a zero scale is rendered (the 0.3 dilation keeps Σ2D definite) and its log-scale gradient is
//!   `s·∂L/∂s = 0`;
//! - non-finite Gaussian parameters, camera or upstream gradients are **refused** with an error
//!   before any work (the forward render skips such Gaussians; an optimiser must not learn from
//!   them).
//!
//! Features are rendered by the forward pass but not differentiated.

use c4g_scene::{Camera, GaussianSet, SceneError};

use super::{Image, RenderOptions};

/// Camera parameters differentiated: `[ωx, ωy, ωz, νx, νy, νz, log focal]`.
pub const CAMERA_GRADIENT_PARAMETERS: usize = 7;

/// The gradient of a loss with respect to a render's planes, row-major like [`Image`]'s.
#[derive(Debug, Clone, Copy)]
pub struct RenderGradients<'a> {
    /// `∂L/∂rgb`, 3 floats a pixel, interleaved.
    pub rgb: &'a [f32],
    /// `∂L/∂alpha`, one a pixel, if the loss reads alpha.
    pub alpha: Option<&'a [f32]>,
    /// `∂L/∂expected depth`, one a pixel, if the loss reads it (where alpha is 0 the expected
    /// depth is the constant 0, so those pixels pass nothing back).
    pub expected_depth: Option<&'a [f32]>,
}

impl<'a> RenderGradients<'a> {
    /// A gradient with respect to colour only.
    pub fn rgb(rgb: &'a [f32]) -> Self {
        Self {
            rgb,
            alpha: None,
            expected_depth: None,
        }
    }

    /// Checks lengths (for a `width × height` image) and finiteness.
    pub fn validate(&self, width: u32, height: u32) -> Result<(), SceneError> {
        let pixels = width as usize * height as usize;
        let planes = [
            ("rgb", Some(self.rgb), 3 * pixels),
            ("alpha", self.alpha, pixels),
            ("expected depth", self.expected_depth, pixels),
        ];
        for (name, plane, len) in planes {
            let Some(plane) = plane else { continue };
            if plane.len() != len {
                return Err(SceneError::InvalidImage(format!(
                    "the {name} gradient holds {} values, expected {len} for {width}x{height}",
                    plane.len()
                )));
            }
            if let Some(i) = plane.iter().position(|v| !v.is_finite()) {
                return Err(SceneError::InvalidImage(format!(
                    "the {name} gradient is not finite at {i}"
                )));
            }
        }
        Ok(())
    }
}

/// The gradient of a loss with respect to every Gaussian, in the optimiser's parametrisation
/// (the module documentation); one entry per Gaussian of the set, in its order.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct GaussianGradients {
    /// `∂L/∂position`.
    pub positions: Vec<[f32; 3]>,
    /// `∂L/∂log scale`.
    pub log_scales: Vec<[f32; 3]>,
    /// `∂L/∂q` of the stored quaternion `w, x, y, z` (through its normalisation).
    pub rotations: Vec<[f32; 4]>,
    /// `∂L/∂logit(opacity)`.
    pub opacity_logits: Vec<f32>,
    /// `∂L/∂colour`.
    pub colors: Vec<[f32; 3]>,
    /// `∂L/∂(u, v)`, the projected centre in pixels: 3DGS's densification signal (its norm, in
    /// pixels; 3DGS's NDC units are these times `(W/2, H/2)`).
    pub means2d: Vec<[f32; 2]>,
}

impl GaussianGradients {
    /// All zero, for `n` Gaussians.
    pub fn zeros(n: usize) -> Self {
        Self {
            positions: vec![[0.0; 3]; n],
            log_scales: vec![[0.0; 3]; n],
            rotations: vec![[0.0; 4]; n],
            opacity_logits: vec![0.0; n],
            colors: vec![[0.0; 3]; n],
            means2d: vec![[0.0; 2]; n],
        }
    }

    /// Number of Gaussians.
    pub fn len(&self) -> usize {
        self.positions.len()
    }

    /// True when there are none.
    pub fn is_empty(&self) -> bool {
        self.positions.is_empty()
    }

    /// Gaussian `i`'s gradient as 14 floats in the order position, log scale, rotation, opacity
    /// logit, colour (the canonical layout's order).
    pub fn row(&self, i: usize) -> [f32; 14] {
        let mut out = [0.0; 14];
        out[0..3].copy_from_slice(&self.positions[i]);
        out[3..6].copy_from_slice(&self.log_scales[i]);
        out[6..10].copy_from_slice(&self.rotations[i]);
        out[10] = self.opacity_logits[i];
        out[11..14].copy_from_slice(&self.colors[i]);
        out
    }
}

/// The gradient of a loss with respect to the camera: `[ωx, ωy, ωz, νx, νy, νz, log focal]` at
/// zero (the module documentation).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct CameraGradients {
    /// `∂L/∂ω`, `∂L/∂ν`, `∂L/∂log focal`.
    pub tangent: [f64; CAMERA_GRADIENT_PARAMETERS],
}

/// Everything one backward pass returns.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Gradients {
    /// Per Gaussian.
    pub gaussians: GaussianGradients,
    /// The camera's (zero unless asked for).
    pub camera: CameraGradients,
}

/// What a backward pass computes besides the Gaussians' gradients.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct BackwardOptions {
    /// Also differentiate with respect to the camera.
    pub camera: bool,
}

/// A rasterizer that can differentiate its renders (the forward model of [`super`]) in reverse
/// mode: a forward pass that keeps what the backward needs, then any number of backward passes
/// over it.
pub trait DifferentiableRasterizer {
    /// What a forward pass keeps for its backward passes; it borrows the set it rendered.
    type Saved<'a>;

    /// Renders like [`super::Rasterizer::render`] (the same image) and keeps what a backward pass
    /// needs. Refuses sets with a non-finite parameter.
    fn render_saved<'a>(
        &self,
        gaussians: &'a GaussianSet,
        camera: &Camera,
        options: &RenderOptions,
    ) -> Result<(Image, Self::Saved<'a>), SceneError>;

    /// The gradient of a loss with respect to the Gaussians (and, with `options.camera`, the
    /// camera) of the render `saved` was kept from, given the loss's gradient with respect to
    /// that render's planes.
    fn backward(
        &self,
        saved: &Self::Saved<'_>,
        upstream: &RenderGradients<'_>,
        options: BackwardOptions,
    ) -> Result<Gradients, SceneError>;
}

/// Refuses a set with a non-finite parameter (features aside: they are not differentiated).
pub fn check_finite(set: &GaussianSet) -> Result<(), SceneError> {
    let finite = |v: &[f32]| v.iter().all(|x| x.is_finite());
    for i in 0..set.len() {
        let ok = finite(&set.positions()[i])
            && finite(&set.scales()[i])
            && finite(&set.rotations()[i])
            && set.opacities()[i].is_finite()
            && finite(&set.colors()[i]);
        if !ok {
            return Err(SceneError::InvalidGaussian {
                index: i,
                reason: "a parameter is not finite: a differentiable render refuses it".to_owned(),
            });
        }
    }
    Ok(())
}
