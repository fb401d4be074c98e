//! The camera Jacobian of a render: the forward model of [`c4g_renderer::raster`] evaluated in f64, and
//! at every pixel the derivatives of its colour (over the background) and alpha with respect to
//! the seven camera parameters ([`CAMERA_PARAMETERS`]): a left-multiplied se(3) perturbation of
//! world-to-camera and the log of a focal scale shared by fx and fy.
//!
//! Forward mode, not the usual reverse pass: what alignment needs is the per-pixel Jacobian (four
//! outputs by seven parameters, for Gauss–Newton's `JᵀJ`), not one loss's gradient, and seven
//! tangents carried front to back alongside the transmittance give all of it in one pass,
//! where reverse mode would need a back-to-front pass per output. With `Tᵢ` the transmittance in
//! front of splat `i` and `wᵢ = αᵢ Tᵢ`:
//! `∂wᵢ = ∂αᵢ Tᵢ + αᵢ ∂Tᵢ`, `∂Tᵢ₊₁ = ∂Tᵢ (1 − αᵢ) − Tᵢ ∂αᵢ`, colour `Σ cᵢ wᵢ + T·bg` and alpha
//! `1 − T`; `∂αᵢ = −αᵢ/2 · ∂d²ᵢ`, and zero where alpha is clamped at 0.99.
//!
//! Held fixed under the derivative, because the render is only piecewise smooth in the camera:
//! the depth order (two overlapping splats swap where their depths cross, and the image jumps),
//! which pixels each splat reaches (the 3-sigma cut, the 3DGS tiles, the 1/255 alpha floor) and
//! where a pixel stops (the transmittance floor). The derivative is exact inside a piece and
//! says nothing about the jumps between pieces; finite differences agree with it wherever a step
//! crosses none. Not modelled at all: lens distortion (the camera is a pinhole, as the forward
//! model is) and the principal point (it stays where the camera has it).
//!
//! Memory: the Jacobian is 4 × 7 f64 a pixel (224 bytes): 11 MB at 224², 0.46 GB at 1080p, which
//! is why alignment runs at the model's resolutions.
//!
//! The same tiling as the CPU rasterizer: splats projected in parallel, sorted by (depth, index),
//! binned into 16-pixel tiles, and rows of tiles composited in parallel with rayon (on the
//! current pool: run it inside `pool.install` to choose one).

use rayon::prelude::*;

use super::adjustment::{CAMERA_PARAMETERS, CameraAdjustment};
use super::splat::{Splat, View, project};
use c4g_renderer::raster::{ALPHA_MAX, ALPHA_MIN, RenderOptions, TILE, TRANSMITTANCE_MIN};
use c4g_scene::{Camera, GaussianSet, SceneError};

const P: usize = CAMERA_PARAMETERS;

/// A render in f64 and its derivatives with respect to the camera, every plane row-major.
#[derive(Debug, Clone, PartialEq)]
pub struct CameraJacobian {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// RGB over the background, 3 values a pixel, interleaved.
    pub rgb: Vec<f64>,
    /// Accumulated opacity `1 − T`.
    pub alpha: Vec<f64>,
    /// `∂rgb / ∂θ`, one row of [`CAMERA_PARAMETERS`] per value of `rgb` (same order).
    pub d_rgb: Vec<[f64; P]>,
    /// `∂alpha / ∂θ`, one row per pixel.
    pub d_alpha: Vec<[f64; P]>,
}

impl CameraJacobian {
    /// The gradient of a per-pixel loss `L(rgb, alpha)` with respect to the camera parameters,
    /// given the loss's derivatives at every value: `∂L/∂rgb` (3 a pixel) and `∂L/∂alpha` (one a
    /// pixel, or `None` for a loss of colour alone).
    ///
    /// Fails (`InvalidImage`) when the lengths are not the image's.
    pub fn gradient(
        &self,
        d_loss_d_rgb: &[f64],
        d_loss_d_alpha: Option<&[f64]>,
    ) -> Result<[f64; P], SceneError> {
        if d_loss_d_rgb.len() != self.rgb.len()
            || d_loss_d_alpha.is_some_and(|a| a.len() != self.alpha.len())
        {
            return Err(SceneError::InvalidImage(format!(
                "a loss's derivatives for a {}x{} render hold {} values for RGB and {} for \
                 alpha; got {} and {}",
                self.width,
                self.height,
                self.rgb.len(),
                self.alpha.len(),
                d_loss_d_rgb.len(),
                d_loss_d_alpha.map_or(0, <[f64]>::len),
            )));
        }
        let mut out = [0.0; P];
        let mut add = |rows: &[[f64; P]], weights: &[f64]| {
            for (row, w) in rows.iter().zip(weights) {
                for (o, d) in out.iter_mut().zip(row) {
                    *o += w * d;
                }
            }
        };
        add(&self.d_rgb, d_loss_d_rgb);
        if let Some(a) = d_loss_d_alpha {
            add(&self.d_alpha, a);
        }
        Ok(out)
    }
}

/// Renders `gaussians` in f64 as the camera `adjustment ∘ camera` sees them, with the derivatives
/// of every pixel with respect to a further left perturbation `exp(θ) ∘ adjustment ∘ camera` at
/// θ = 0 (the focal parameter included, whether or not a caller refines it).
///
/// The image is the forward model's (`raster` module documentation) in f64: it agrees with the
/// float64 reference (`models/python/c4g/raster/reference.py`) to 1e-6 on the fixture scenes,
/// and with the [`c4g_renderer::CpuRasterizer`]'s f32 render to that one's tolerance (2e-3). Features, depth and
/// contributions are not rendered.
///
/// Fails on invalid render options or an adjustment with non-finite numbers.
pub fn camera_jacobian(
    gaussians: &GaussianSet,
    camera: &Camera,
    adjustment: &CameraAdjustment,
    options: &RenderOptions,
) -> Result<CameraJacobian, SceneError> {
    options.validate()?;
    if !adjustment.is_finite() {
        return Err(SceneError::InvalidCamera(format!(
            "the camera adjustment {adjustment:?} is not finite"
        )));
    }
    Ok(render(gaussians, camera, adjustment, options))
}

/// [`camera_jacobian`] on checked inputs.
pub(super) fn render(
    set: &GaussianSet,
    camera: &Camera,
    adjustment: &CameraAdjustment,
    options: &RenderOptions,
) -> CameraJacobian {
    let view = View::new(camera, adjustment, options);
    let mut splats: Vec<Splat> = (0..set.len())
        .into_par_iter()
        .filter_map(|i| project(&view, set, i))
        .collect();
    splats.par_sort_unstable_by_key(|s| s.key);
    let (width, height) = (view.width as usize, view.height as usize);
    let bins = Bins::new(view.width, view.height, &splats);
    let pixels = width * height;
    let mut out = CameraJacobian {
        width: view.width,
        height: view.height,
        rgb: vec![0.0; pixels * 3],
        alpha: vec![0.0; pixels],
        d_rgb: vec![[0.0; P]; pixels * 3],
        d_alpha: vec![[0.0; P]; pixels],
    };
    let band = TILE as usize * width;
    let background = options.background.map(f64::from);
    out.rgb
        .par_chunks_mut(band * 3)
        .zip(out.alpha.par_chunks_mut(band))
        .zip(out.d_rgb.par_chunks_mut(band * 3))
        .zip(out.d_alpha.par_chunks_mut(band))
        .enumerate()
        .for_each(|(ty, (((rgb, alpha), d_rgb), d_alpha))| {
            let mut band = Band {
                rgb,
                alpha,
                d_rgb,
                d_alpha,
            };
            let mut tile = TileState::new();
            for tx in 0..bins.tiles_x {
                let t = ty * bins.tiles_x + tx;
                let rect = bins.rect(t);
                tile.clear();
                tile.composite(&rect, &bins.lists[t], &splats);
                tile.write(&rect, width, background, &mut band);
            }
        });
    out
}

/// The planes of one band of `TILE` image rows, for one task to write.
struct Band<'a> {
    rgb: &'a mut [f64],
    alpha: &'a mut [f64],
    d_rgb: &'a mut [[f64; P]],
    d_alpha: &'a mut [[f64; P]],
}

/// Splats per tile, each list in depth order.
struct Bins {
    width: u32,
    height: u32,
    tiles_x: usize,
    /// Indices into the sorted splats, per tile (row-major).
    lists: Vec<Vec<u32>>,
}

impl Bins {
    /// Every (tile, splat) pair, as a list per tile: alignment renders C4G's sets (thousands of
    /// Gaussians at a few hundred pixels), far from the pair counts the rasterizer's bands exist
    /// for.
    fn new(width: u32, height: u32, splats: &[Splat]) -> Self {
        let tiles_x = width.div_ceil(TILE) as usize;
        let tiles_y = height.div_ceil(TILE) as usize;
        let mut lists = vec![Vec::new(); tiles_x * tiles_y];
        for (k, s) in splats.iter().enumerate() {
            for ty in (s.y0 / TILE) as usize..=(s.y1 / TILE) as usize {
                for tx in (s.x0 / TILE) as usize..=(s.x1 / TILE) as usize {
                    lists[ty * tiles_x + tx].push(k as u32);
                }
            }
        }
        Self {
            width,
            height,
            tiles_x,
            lists,
        }
    }

    fn rect(&self, t: usize) -> Rect {
        let (tx, ty) = ((t % self.tiles_x) as u32, (t / self.tiles_x) as u32);
        let (x0, y0) = (tx * TILE, ty * TILE);
        Rect {
            x0,
            y0,
            w: TILE.min(self.width - x0),
            h: TILE.min(self.height - y0),
        }
    }
}

/// A tile's pixels: `(x0, y0)` its corner, `w × h` its size.
struct Rect {
    x0: u32,
    y0: u32,
    w: u32,
    h: u32,
}

const TILE_PIXELS: usize = (TILE * TILE) as usize;

/// One tile's running compositing state with its tangents, pixel `(x, y)` of the tile at
/// `y · TILE + x`.
struct TileState {
    rgb: [[f64; 3]; TILE_PIXELS],
    d_rgb: [[[f64; P]; 3]; TILE_PIXELS],
    transmittance: [f64; TILE_PIXELS],
    d_transmittance: [[f64; P]; TILE_PIXELS],
    done: [bool; TILE_PIXELS],
}

impl TileState {
    fn new() -> Box<Self> {
        Box::new(Self {
            rgb: [[0.0; 3]; TILE_PIXELS],
            d_rgb: [[[0.0; P]; 3]; TILE_PIXELS],
            transmittance: [1.0; TILE_PIXELS],
            d_transmittance: [[0.0; P]; TILE_PIXELS],
            done: [false; TILE_PIXELS],
        })
    }

    fn clear(&mut self) {
        self.rgb = [[0.0; 3]; TILE_PIXELS];
        self.d_rgb = [[[0.0; P]; 3]; TILE_PIXELS];
        self.transmittance = [1.0; TILE_PIXELS];
        self.d_transmittance = [[0.0; P]; TILE_PIXELS];
        self.done = [false; TILE_PIXELS];
    }

    /// Front to back over `list` (indices into `splats`), the forward model's rules per pixel:
    /// the footprint's cut, the 1/255 floor, the 0.99 clamp, the stop before `T` falls below
    /// 1e-4.
    fn composite(&mut self, rect: &Rect, list: &[u32], splats: &[Splat]) {
        for &k in list {
            let s = &splats[k as usize];
            let (px0, px1) = (s.x0.max(rect.x0), s.x1.min(rect.x0 + rect.w - 1));
            let (py0, py1) = (s.y0.max(rect.y0), s.y1.min(rect.y0 + rect.h - 1));
            for py in py0..=py1 {
                for px in px0..=px1 {
                    let p = ((py - rect.y0) * TILE + (px - rect.x0)) as usize;
                    if !self.done[p] {
                        self.blend(p, s, f64::from(px) + 0.5, f64::from(py) + 0.5);
                    }
                }
            }
        }
    }

    fn blend(&mut self, p: usize, s: &Splat, x: f64, y: f64) {
        // The cuts first, from d² alone: most pixels of a box fail one.
        let d2 = s.d2(x, y);
        if d2 > s.cut {
            return;
        }
        let raw = s.opacity * (-0.5 * d2).exp();
        if raw < f64::from(ALPHA_MIN) {
            return;
        }
        let t = self.transmittance[p];
        let clamped = raw > f64::from(ALPHA_MAX);
        let alpha = if clamped { f64::from(ALPHA_MAX) } else { raw };
        let t_next = t * (1.0 - alpha);
        if t_next < f64::from(TRANSMITTANCE_MIN) {
            self.done[p] = true;
            return;
        }
        let mut d_alpha = [0.0; P];
        if !clamped {
            let (_, d_d2) = s.mahalanobis(x, y);
            for (da, dd) in d_alpha.iter_mut().zip(d_d2) {
                *da = -0.5 * alpha * dd;
            }
        }
        let weight = alpha * t;
        let dt = &mut self.d_transmittance[p];
        let mut d_weight = [0.0; P];
        for k in 0..P {
            d_weight[k] = d_alpha[k] * t + alpha * dt[k];
            dt[k] = dt[k] * (1.0 - alpha) - t * d_alpha[k];
        }
        for c in 0..3 {
            self.rgb[p][c] += weight * s.color[c];
            for (d, dw) in self.d_rgb[p][c].iter_mut().zip(d_weight) {
                *d += dw * s.color[c];
            }
        }
        self.transmittance[p] = t_next;
    }

    /// Writes the tile into a band of `TILE` image rows (the band's own planes), the background
    /// under what remains.
    fn write(&self, rect: &Rect, width: usize, background: [f64; 3], band: &mut Band<'_>) {
        for ly in 0..rect.h as usize {
            for lx in 0..rect.w as usize {
                let p = ly * TILE as usize + lx;
                let q = ly * width + rect.x0 as usize + lx;
                let (t, dt) = (self.transmittance[p], self.d_transmittance[p]);
                for (c, bg) in background.iter().enumerate() {
                    band.rgb[3 * q + c] = self.rgb[p][c] + t * bg;
                    for (out, (d, d_t)) in band.d_rgb[3 * q + c]
                        .iter_mut()
                        .zip(self.d_rgb[p][c].iter().zip(dt))
                    {
                        *out = d + d_t * bg;
                    }
                }
                band.alpha[q] = 1.0 - t;
                band.d_alpha[q] = dt.map(|v| -v);
            }
        }
    }
}
