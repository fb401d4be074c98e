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
//!   centre `(i + 0.5, j + 0.5)`, where the Mahalanobis distance `d` of the centre under `Σ2D`
//!   gives `alpha = min(ALPHA_MAX, opacity · exp(-d²/2))`, and `alpha < ALPHA_MIN` contributes
//!   nothing;
//! - which pixels a Gaussian is evaluated at is its [`Footprint`] ([`RenderOptions::footprint`]):
//!   - [`Footprint::Ellipse`] (the default): the pixels with `d ≤` [`SIGMA_EXTENT`];
//!   - [`Footprint::Tiles3dgs`], the rule of the original 3DGS CUDA rasterizer
//!     (`diff_gaussian_rasterization`, which the public C4G code renders with): with `Σ2D =
//!     [[a, b], [b, c]]`, `λ = (a + c)/2 + √max(`[`DISCRIMINANT_FLOOR_3DGS`]`, ((a − c)/2)² + b²)`
//!     (3DGS writes the discriminant `mid² − det`: the same number, here without f32
//!     cancellation), the radius `r = ⌈3·√λ⌉` pixels and, with `p = (u − 0.5, v − 0.5)` (3DGS's
//!     pixel coordinates, where pixel `i` sits at `i`), the tiles of [`TILE_3DGS`] pixels
//!     `[⌊(p − r)/16⌋, ⌊(p + r + 15)/16⌋)` on each axis, both ends clamped to `[0, tiles]`;
//!     every pixel of those tiles is evaluated, with no cut at 3 sigma (3DGS also skips where the
//!     exponent `-d²/2` is positive, which never happens in exact arithmetic); a Gaussian whose
//!     tile range is empty is skipped. Beyond 3 sigma, where the ellipse cuts, its fringe (alpha
//!     up to `opacity · e^-4.5 ≈ 0.011 · opacity`, down to [`ALPHA_MIN`]) is drawn inside its
//!     tiles. Its tiles are not quite the square `p ± r`: where `p + r` lies less than a pixel
//!     past a multiple of 16, the last pixel column (row) of the square is left out, even inside
//!     3 sigma;
//! - front to back by camera-space depth (ties by index); a pixel stops before the Gaussian that
//!   would bring its transmittance `T` below [`TRANSMITTANCE_MIN`];
//! - outputs: colour `Σ cᵢ αᵢ Tᵢ + T·background`, alpha `1 - T`, depth `Σ zᵢ αᵢ Tᵢ`
//!   (alpha-weighted), expected depth `depth / alpha` (0 where alpha is 0), and any per-Gaussian
//!   feature channels composited like colour (no background).
//!
//! Where [`Footprint::Tiles3dgs`] still differs from `diff_gaussian_rasterization`, by design:
//! - near and far: 3DGS culls a Gaussian whose camera-space depth is `≤ 0.2` (hard-coded, whatever
//!   its projection matrix's near plane) and has no far plane; here `[near, far]` of
//!   [`RenderOptions`] (0.01 and 100 by default) decide, in both footprints (`near: 0.2` gives
//!   3DGS's cull but for a depth of exactly 0.2, which is drawn here);
//! - the principal point: 3DGS's projection puts it at the image centre; here it is `(cx, cy)`
//!   (the same where `cx = W/2`, `cy = H/2`, as C4G's cameras have it);
//! - precision: 3DGS computes in f32 (with the cancelling `mid² − det`); the rule here is its exact
//!   arithmetic (the CPU rasterizer projects in f64, the wgpu one in rescaled f32), so a radius or
//!   tile end that f32 rounds across an integer can move a tile row or column of one Gaussian;
//! - non-finite parameters and a zero rotation skip the Gaussian here (3DGS computes with them);
//!   3DGS skips a determinant of exactly 0 where this skips one that is not positive and finite;
//! - outputs: 3DGS renders colour (over its background) only; alpha, depth, expected depth and
//!   features are this model's.
//!
//! The same in both footprints, and in 3DGS: the 0.3 low-pass dilation ([`EPS2D`], in the
//! determinant as well, with no opacity compensation: only the later `antialiasing` option of 3DGS
//! adds one), the FOV clamp, the alpha clamp 0.99 and the 1/255 skip, the stop before `T` would
//! fall below 1e-4 (that Gaussian and all behind it are not composited), front-to-back order by
//! camera-space depth with ties by index (3DGS's stable radix sort of keys written in index
//! order).
//!
//! The float64 reference of the same model, both footprints, is
//! `models/python/c4g/raster/reference.py`. Its gradients ([`grad`]: the interface, the
//! conventions where the model is not smooth; the CPU backward pass beside the forward one) are
//! held to `models/python/c4g/raster/grad_reference.py` (float64 autograd).

mod cpu;
#[cfg(feature = "gpu")]
pub mod gpu;
pub mod grad;
mod model;

pub use cpu::tiles_3dgs;
pub use cpu::{CpuRasterizer, CpuSaved, PAIR_BUDGET, PixelWeight, TILE};
pub use grad::{
    BackwardOptions, CameraGradients, DifferentiableRasterizer, GaussianGradients, Gradients,
    RenderGradients,
};
pub use model::{
    ALPHA_MAX, ALPHA_MIN, DISCRIMINANT_FLOOR_3DGS, EPS2D, FAR, FOV_CLAMP, FeatureImage, Image,
    NEAR, Rasterizer, RenderOptions, SIGMA_EXTENT, TILE_3DGS, TRANSMITTANCE_MIN,
};
