//! The backward pass of the CPU rasterizer: reverse-mode gradients of a render with respect to
//! every Gaussian (and optionally the camera), the 3DGS backward on threads.
//!
//! The forward pass ([`super::CpuRasterizer`]'s `render_saved`) keeps, per pixel, only the final
//! transmittance and one past the list position of the last splat it composited there, so memory
//! is O(pixels), not O(pixels × splats). The backward pass then:
//! 1. re-bins the kept splats (the same bands and tile lists as the forward pass: binning is cheap
//!    and keeping the pairs would cost more memory than recomputing them);
//! 2. walks each tile's list **back to front** (tiles in parallel, by rows like the forward pass),
//!    visiting exactly the (pixel, splat) pairs the forward pass composited: the same row culls
//!    and the same f32 decisions (`blend::row_reach`, `blend::sample`), and at each pixel only
//!    the splats in front of its last one. Each pixel recovers `Tᵢ = Tᵢ₊₁ / (1 − αᵢ)` and keeps the
//!    colour and depth composited behind the current splat, so `∂C/∂αᵢ = Tᵢ cᵢ − Bᵢ / (1 − αᵢ)`
//!    with `Bᵢ = Σ_{j>i} cⱼ wⱼ + T·background` (and `∂alpha/∂αᵢ = T / (1 − αᵢ)`, `T` the final
//!    transmittance); per splat and tile it sums the
//!    gradients of its 2D centre, conic, opacity, colour and depth in f32 (at most 256 pixels),
//!    then the tiles' sums are reduced per splat in f64, in a fixed order (deterministic whatever
//!    the threads);
//! 3. pushes each splat's 2D gradients through the projection in f64 (`project::View::ewa`'s
//!    intermediates): conic → `Σ2D` (`∂L/∂Σ = −K G K`) → `M = J W R S` → the Jacobian `J` (depth
//!    and the FOV clamp's branch), the centre, the rotation (through the normalisation) and the
//!    log scale; and, when asked, the camera's left se(3) increment and log focal.
//!
//! Threads: the forward pass's (the rasterizer's pool; tiles by rows of tiles in parallel, then
//! splats in parallel through the projection). No allocation per pixel or splat: each row task
//! holds one tile state and one growing list of per-splat sums. The conventions where the forward
//! model is not smooth are `raster::grad`'s.

use glam::{DMat3, DVec3};
use rayon::prelude::*;

use super::bin::TileGrid;
use super::blend::{RowReach, Sample, d2_cut, row_reach, sample, widened_reach2};
use super::frame::{Frame, blend_frame};
use super::project::{Ewa, Splat, View};
use super::tiling::TILE;
use crate::raster::grad::{
    BackwardOptions, CAMERA_GRADIENT_PARAMETERS, CameraGradients, GaussianGradients, Gradients,
    RenderGradients,
};
use crate::raster::{Image, RenderOptions};
use c4g_scene::{Camera, GaussianSet};

/// Pixels in a tile.
const TILE_PIXELS: usize = (TILE * TILE) as usize;

/// What a CPU forward pass keeps for its backward passes.
pub struct CpuSaved<'a> {
    set: &'a GaussianSet,
    options: RenderOptions,
    frame: Frame,
    /// Per pixel: the final transmittance, one past the list position of the last composited
    /// splat, and the alpha-weighted depth.
    final_t: Vec<f32>,
    last: Vec<u32>,
    depth: Vec<f32>,
}

impl CpuSaved<'_> {
    /// The set that was rendered.
    pub fn gaussians(&self) -> &GaussianSet {
        self.set
    }

    /// Width and height of the render.
    pub fn size(&self) -> (u32, u32) {
        (self.frame.grid.width, self.frame.grid.height)
    }
}

/// The forward pass that keeps what the backward needs (on the current rayon pool).
pub(super) fn render_saved<'a>(
    set: &'a GaussianSet,
    camera: &Camera,
    options: &RenderOptions,
    pair_budget: usize,
) -> (Image, CpuSaved<'a>) {
    let frame = Frame::new(set, camera, options);
    let pixels = frame.grid.pixels();
    let mut final_t = vec![1.0f32; pixels];
    let mut last = vec![0u32; pixels];
    let (image, _) = blend_frame(
        &frame,
        set,
        options,
        pair_budget,
        false,
        Some((&mut final_t, &mut last)),
    );
    let depth = image.depth.clone();
    let saved = CpuSaved {
        set,
        options: options.clone(),
        frame,
        final_t,
        last,
        depth,
    };
    (image, saved)
}

/// Sums over a tile's pixels for one splat: `[∂L/∂u, ∂L/∂v, ∂L/∂K₀₀, ∂L/∂K₀₁, ∂L/∂opacity,
/// ∂L/∂r, ∂L/∂g, ∂L/∂b, ∂L/∂depth, ∂L/∂K₁₁]`, `K = Σ2D⁻¹` the conic (`∂L/∂K₀₁` is the
/// full-matrix gradient's, each off-diagonal entry's own).
type Grad2d = [f32; 10];

/// Per-pixel state of a tile's walk back to front, pixel `(x, y)` of the tile at `y · TILE + x`.
struct TileBack {
    /// Transmittance after the splat being visited (before: the final one).
    t_after: [f32; TILE_PIXELS],
    t_final: [f32; TILE_PIXELS],
    /// Colour and depth composited behind the splat being visited (the background included).
    behind_rgb: [[f32; 3]; TILE_PIXELS],
    behind_depth: [f32; TILE_PIXELS],
    /// The upstream gradient there: colour, and alpha and depth with the expected depth's
    /// folded in.
    g_rgb: [[f32; 3]; TILE_PIXELS],
    g_alpha: [f32; TILE_PIXELS],
    g_depth: [f32; TILE_PIXELS],
    last: [u32; TILE_PIXELS],
}

impl TileBack {
    fn new() -> Box<Self> {
        Box::new(Self {
            t_after: [1.0; TILE_PIXELS],
            t_final: [1.0; TILE_PIXELS],
            behind_rgb: [[0.0; 3]; TILE_PIXELS],
            behind_depth: [0.0; TILE_PIXELS],
            g_rgb: [[0.0; 3]; TILE_PIXELS],
            g_alpha: [0.0; TILE_PIXELS],
            g_depth: [0.0; TILE_PIXELS],
            last: [0; TILE_PIXELS],
        })
    }

    /// Loads tile `t`'s pixels from the forward pass's state and the upstream gradients; returns
    /// the largest `last` in the tile (splats at or past it composited nowhere here).
    fn load(
        &mut self,
        grid: &TileGrid,
        t: usize,
        saved: &CpuSaved<'_>,
        upstream: &RenderGradients<'_>,
    ) -> u32 {
        let (x0, y0, w, h) = grid.rect(t);
        let width = grid.width as usize;
        let background = saved.options.background;
        self.last = [0; TILE_PIXELS];
        let mut most = 0;
        for ly in 0..h as usize {
            for lx in 0..w as usize {
                let p = ly * TILE as usize + lx;
                let q = (y0 as usize + ly) * width + x0 as usize + lx;
                let t_final = saved.final_t[q];
                self.t_after[p] = t_final;
                self.t_final[p] = t_final;
                self.behind_rgb[p] = background.map(|b| t_final * b);
                self.behind_depth[p] = 0.0;
                self.g_rgb[p] = [
                    upstream.rgb[3 * q],
                    upstream.rgb[3 * q + 1],
                    upstream.rgb[3 * q + 2],
                ];
                let mut g_alpha = upstream.alpha.map_or(0.0, |a| a[q]);
                let mut g_depth = 0.0;
                // Expected depth E = D / A (A = 1 − T, as the forward pass writes it), 0 where A
                // is 0.
                let alpha = 1.0 - t_final;
                if let Some(g_e) = upstream.expected_depth.map(|e| e[q])
                    && alpha > 0.0
                {
                    g_depth += g_e / alpha;
                    g_alpha -= g_e * saved.depth[q] / (alpha * alpha);
                }
                self.g_alpha[p] = g_alpha;
                self.g_depth[p] = g_depth;
                self.last[p] = saved.last[q];
                most = most.max(saved.last[q]);
            }
        }
        most
    }
}

/// Walks the `list` (indices into `splats`, front to back) of the tile whose pixel rectangle is
/// `(x0, y0, w, h)` back to front, appending each splat's sums over the tile's pixels to `out` as
/// (index into `splats`, sums); splats at list positions from `end` on composited nowhere here.
fn backward_tile(
    state: &mut TileBack,
    (x0, y0, w, h): (u32, u32, u32, u32),
    list: &[u32],
    splats: &[Splat],
    cut: f32,
    end: u32,
    out: &mut Vec<(u32, Grad2d)>,
) {
    let end = (end as usize).min(list.len());
    for (position, &index) in list[..end].iter().enumerate().rev() {
        let s = &splats[index as usize];
        let position = position as u32;
        let reach2 = widened_reach2(s);
        // The conic as the f32 test computes d²: a·(dx − k·dy)² + inv_syy·dy².
        let mut g: Grad2d = [0.0; 10];
        let mut any = false;
        for py in s.y0.max(y0)..=s.y1.min(y0 + h - 1) {
            let Some(RowReach {
                dy,
                row_d2,
                centre,
                lo,
                hi,
            }) = row_reach(s, py, reach2)
            else {
                continue;
            };
            let row = ((py - y0) * TILE) as usize;
            for px in lo.max(x0)..=hi.min(x0 + w - 1) {
                let p = (row + (px - x0) as usize) & (TILE_PIXELS - 1);
                if position >= state.last[p] {
                    continue;
                }
                let Some(Sample {
                    dx,
                    gauss,
                    alpha,
                    clamped,
                }) = sample(s, px, centre, row_d2, cut)
                else {
                    continue;
                };
                any = true;
                let one_minus = 1.0 - alpha;
                let t_here = state.t_after[p] / one_minus;
                let weight = alpha * t_here;
                let g_rgb = state.g_rgb[p];
                let g_depth = state.g_depth[p];
                let behind = state.behind_rgb[p];
                let mut front = g_depth * s.depth;
                let mut back =
                    g_depth * state.behind_depth[p] - state.g_alpha[p] * state.t_final[p];
                for c in 0..3 {
                    g[5 + c] += g_rgb[c] * weight;
                    front += g_rgb[c] * s.color[c];
                    back += g_rgb[c] * behind[c];
                    state.behind_rgb[p][c] = behind[c] + s.color[c] * weight;
                }
                g[8] += g_depth * weight;
                state.behind_depth[p] += s.depth * weight;
                state.t_after[p] = t_here;
                if clamped {
                    continue;
                }
                let g_alpha = t_here * front - back / one_minus;
                g[4] += g_alpha * gauss;
                // α = o·exp(−d²/2): ∂α/∂d² = −α/2.
                let g_d2 = -0.5 * alpha * g_alpha;
                // d² = a·e² + inv_syy·dy² with e = dx − k·dy, dx = x − u, dy = y − v.
                let e = dx - centre;
                g[0] -= g_d2 * 2.0 * s.a * e;
                g[1] -= g_d2 * 2.0 * (s.inv_syy * dy - s.a * s.k * e);
                g[2] += g_d2 * dx * dx;
                g[3] += g_d2 * dx * dy;
                g[9] += g_d2 * dy * dy;
            }
        }
        if any {
            out.push((index, g));
        }
    }
}

/// The whole backward pass on the current rayon pool. `upstream` is validated.
pub(super) fn backward(
    saved: &CpuSaved<'_>,
    upstream: &RenderGradients<'_>,
    options: BackwardOptions,
    pair_budget: usize,
) -> Gradients {
    let Frame {
        view,
        splats,
        grid,
        chunks,
    } = &saved.frame;
    let cut = d2_cut(saved.options.footprint);
    // Per sorted splat, the tiles' sums in f64, laid out as `Grad2d`.
    let mut sums = vec![[0.0f64; 10]; splats.len()];
    for band in grid.bands(&chunks.totals, pair_budget) {
        let pairs = chunks.fill_band(grid, splats, band.clone());
        let (first, last) = (band.start / grid.tiles_x, (band.end - 1) / grid.tiles_x);
        let partial: Vec<Vec<(u32, Grad2d)>> = (first..=last)
            .into_par_iter()
            .map(|row| {
                let mut state = TileBack::new();
                let mut local = Vec::new();
                let tiles =
                    (row * grid.tiles_x).max(band.start)..((row + 1) * grid.tiles_x).min(band.end);
                for t in tiles {
                    let k = t - band.start;
                    let end = state.load(grid, t, saved, upstream);
                    backward_tile(
                        &mut state,
                        grid.rect(t),
                        &pairs.splats[pairs.offsets[k]..pairs.offsets[k + 1]],
                        splats,
                        cut,
                        end,
                        &mut local,
                    );
                }
                local
            })
            .collect();
        for (index, g) in partial.into_iter().flatten() {
            // The same order every run: rows in order, tiles in order, splats back to front.
            for (sum, v) in sums[index as usize].iter_mut().zip(g) {
                *sum += f64::from(v);
            }
        }
    }
    let per_splat: Vec<(u32, GaussianRow, [f64; CAMERA_GRADIENT_PARAMETERS])> = splats
        .par_iter()
        .zip(&sums)
        .filter(|(_, g)| g.iter().any(|v| *v != 0.0))
        .filter_map(|(s, g)| {
            let g2d = Splat2dGrad {
                centre: [g[0], g[1]],
                conic: [g[2], g[3], g[9]],
                opacity: g[4],
                color: [g[5], g[6], g[7]],
                depth: g[8],
            };
            let ewa = view.ewa(saved.set, s.index as usize)?;
            let (row, cam) = project_backward(view, saved.set, s.index as usize, &ewa, &g2d);
            Some((s.index, row, if options.camera { cam } else { [0.0; 7] }))
        })
        .collect();
    let mut out = GaussianGradients::zeros(saved.set.len());
    let mut tangent = [0.0f64; CAMERA_GRADIENT_PARAMETERS];
    for (index, row, cam) in per_splat {
        let i = index as usize;
        out.positions[i] = row.position;
        out.log_scales[i] = row.log_scale;
        out.rotations[i] = row.rotation;
        out.opacity_logits[i] = row.opacity_logit;
        out.colors[i] = row.color;
        out.means2d[i] = row.mean2d;
        for (t, c) in tangent.iter_mut().zip(cam) {
            *t += c;
        }
    }
    Gradients {
        gaussians: out,
        camera: CameraGradients { tangent },
    }
}

/// A splat's gradients in screen space, summed over its pixels.
struct Splat2dGrad {
    /// `∂L/∂(u, v)`.
    centre: [f64; 2],
    /// `∂L/∂K` of the conic: entries 00, 01 (each of the two off-diagonal ones), 11.
    conic: [f64; 3],
    opacity: f64,
    color: [f64; 3],
    depth: f64,
}

/// One Gaussian's gradients in the optimiser's parametrisation.
struct GaussianRow {
    position: [f32; 3],
    log_scale: [f32; 3],
    rotation: [f32; 4],
    opacity_logit: f32,
    color: [f32; 3],
    mean2d: [f32; 2],
}

/// Pushes one splat's screen-space gradients through its projection (in f64): the Gaussian's
/// gradients, and its share of the camera's.
fn project_backward(
    view: &View,
    set: &GaussianSet,
    i: usize,
    ewa: &Ewa,
    g: &Splat2dGrad,
) -> (GaussianRow, [f64; CAMERA_GRADIENT_PARAMETERS]) {
    let Ewa {
        p_cam,
        unit,
        norm,
        tx,
        ty,
        j0,
        j1,
        wrs,
        m0,
        m1,
        sxx,
        sxy,
        syy,
        det,
        ..
    } = *ewa;
    let (x, y, z) = (p_cam.x, p_cam.y, p_cam.z);
    let (fx, fy) = (view.fx, view.fy);

    // Conic K = Σ⁻¹ = [[syy, −sxy], [−sxy, sxx]] / det; ∂L/∂Σ = −K G K (G the conic's gradient).
    let (k00, k01, k11) = (syy / det, -sxy / det, sxx / det);
    let [g00, g01, g11] = g.conic;
    // K G, then (K G) K.
    let (a00, a01, a10, a11) = (
        k00 * g00 + k01 * g01,
        k00 * g01 + k01 * g11,
        k01 * g00 + k11 * g01,
        k01 * g01 + k11 * g11,
    );
    let s00 = -(a00 * k00 + a01 * k01);
    let s01 = -(a00 * k01 + a01 * k11);
    let s10 = -(a10 * k00 + a11 * k01);
    let s11 = -(a10 * k01 + a11 * k11);
    let s01 = 0.5 * (s01 + s10);
    // Σ = M Mᵀ + ε·I with M's rows m0, m1: ∂L/∂M = 2 (∂L/∂Σ) M.
    let gm0 = 2.0 * (s00 * m0 + s01 * m1);
    let gm1 = 2.0 * (s01 * m0 + s11 * m1);
    // m_r = Vᵀ j_r with V = W R S: ∂L/∂V = Σ_r j_r ⊗ gm_r, ∂L/∂j_r = V gm_r.
    let g_v = outer(j0, gm0) + outer(j1, gm1);
    let gj0 = wrs * gm0;
    let gj1 = wrs * gm1;

    // J = [[fx/z, 0, −fx·tx/z²], [0, fy/z, −fy·ty/z²]], tx = clamp(x/z)·z.
    let mut g_cam = DVec3::ZERO;
    let z2 = z * z;
    let z3 = z2 * z;
    g_cam.z += -gj0.x * fx / z2 + 2.0 * gj0.z * fx * tx / z3;
    g_cam.z += -gj1.y * fy / z2 + 2.0 * gj1.z * fy * ty / z3;
    let g_tx = -gj0.z * fx / z2;
    let g_ty = -gj1.z * fy / z2;
    // Inside the FOV limit tx = x; clamped, tx = ±lim·z (the derivative at the limit is the
    // inside one).
    let inside_x = (x / z).abs() <= view.lim_x;
    let inside_y = (y / z).abs() <= view.lim_y;
    if inside_x {
        g_cam.x += g_tx;
    } else {
        g_cam.z += g_tx * tx / z;
    }
    if inside_y {
        g_cam.y += g_ty;
    } else {
        g_cam.z += g_ty * ty / z;
    }
    // u = fx·x/z + cx, v = fy·y/z + cy, and the depth composited.
    let [gu, gv] = g.centre;
    g_cam.x += gu * fx / z;
    g_cam.y += gv * fy / z;
    g_cam.z += -gu * fx * x / z2 - gv * fy * y / z2 + g.depth;

    // p_cam = W p + t.
    let g_position = view.rotation.transpose() * g_cam;
    // V = W N, N = R S.
    let g_n = view.rotation.transpose() * g_v;
    let r = DMat3::from_quat(unit);
    let s = set.scales()[i].map(f64::from);
    let mut g_r = [[0.0f64; 3]; 3];
    let mut g_log_scale = [0.0f64; 3];
    for k in 0..3 {
        let (gcol, rcol) = (g_n.col(k), r.col(k));
        for row in 0..3 {
            g_r[row][k] = gcol[row] * s[k];
        }
        g_log_scale[k] = s[k] * gcol.dot(rcol);
    }
    let g_unit = rotation_backward(unit.w, unit.x, unit.y, unit.z, &g_r);
    // Through q̂ = q/|q|: ∂L/∂q = (I − q̂q̂ᵀ) ∂L/∂q̂ / |q|.
    let q = [unit.w, unit.x, unit.y, unit.z];
    let along: f64 = q.iter().zip(&g_unit).map(|(a, b)| a * b).sum();
    let g_rotation = [0, 1, 2, 3].map(|k| ((g_unit[k] - q[k] * along) / norm) as f32);
    let o = f64::from(set.opacities()[i]);

    // The camera: p_cam moves by ω × p_cam + ν, V by ω × (each column), and the focal scale
    // multiplies fx and fy (through a clamped coordinate fx·tx stays put).
    let mut omega = p_cam.cross(g_cam);
    for k in 0..3 {
        omega += wrs.col(k).cross(g_v.col(k));
    }
    let mut log_focal = gu * fx * x / z + gv * fy * y / z;
    log_focal += gj0.x * fx / z + gj1.y * fy / z;
    if inside_x {
        log_focal += -gj0.z * fx * tx / z2;
    }
    if inside_y {
        log_focal += -gj1.z * fy * ty / z2;
    }
    let camera = [
        omega.x, omega.y, omega.z, g_cam.x, g_cam.y, g_cam.z, log_focal,
    ];
    let row = GaussianRow {
        position: g_position.to_array().map(|v| v as f32),
        log_scale: g_log_scale.map(|v| v as f32),
        rotation: g_rotation,
        opacity_logit: (g.opacity * o * (1.0 - o)) as f32,
        color: g.color.map(|v| v as f32),
        mean2d: g.centre.map(|v| v as f32),
    };
    (row, camera)
}

/// `a ⊗ b`: the matrix whose entry (row i, column j) is `aᵢ bⱼ`.
fn outer(a: DVec3, b: DVec3) -> DMat3 {
    DMat3::from_cols(a * b.x, a * b.y, a * b.z)
}

/// `∂L/∂(w, x, y, z)` of a unit quaternion from `∂L/∂R` (row-major) of its rotation matrix
/// `R = [[1−2(y²+z²), 2(xy−wz), 2(xz+wy)], [2(xy+wz), 1−2(x²+z²), 2(yz−wx)],
/// [2(xz−wy), 2(yz+wx), 1−2(x²+y²)]]`, the quaternion read as independent variables.
fn rotation_backward(w: f64, x: f64, y: f64, z: f64, g: &[[f64; 3]; 3]) -> [f64; 4] {
    let gw =
        2.0 * (-z * g[0][1] + y * g[0][2] + z * g[1][0] - x * g[1][2] - y * g[2][0] + x * g[2][1]);
    let gx = 2.0
        * (y * g[0][1] + z * g[0][2] + y * g[1][0] - 2.0 * x * g[1][1] - w * g[1][2]
            + z * g[2][0]
            + w * g[2][1]
            - 2.0 * x * g[2][2]);
    let gy = 2.0
        * (-2.0 * y * g[0][0] + x * g[0][1] + w * g[0][2] + x * g[1][0] + z * g[1][2]
            - w * g[2][0]
            + z * g[2][1]
            - 2.0 * y * g[2][2]);
    let gz = 2.0
        * (-2.0 * z * g[0][0] - w * g[0][1] + x * g[0][2] + w * g[1][0] - 2.0 * z * g[1][1]
            + y * g[1][2]
            + x * g[2][0]
            + y * g[2][1]);
    [gw, gx, gy, gz]
}
