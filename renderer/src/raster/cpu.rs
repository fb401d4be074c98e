//! The CPU rasterizer: the forward model of [`super`] on threads, for machines without a GPU and as
//! a second implementation to hold the wgpu one against.
//!
//! Three stages, the 3DGS layout on a CPU:
//! 1. **Project** every Gaussian (in parallel, in f64: huge or tiny scales and focal lengths make
//!    f32 covariances overflow or cancel) to a `Splat`: its pixel centre, its 2D covariance in a
//!    form whose Mahalanobis distance is a sum of non-negative terms, its depth and a
//!    conservative pixel box around the pixels its exact test can reach. Invalid ones are dropped
//!    here.
//! 2. **Bin** splats into 16×16-pixel tiles. Splats are sorted once by (depth, index); a stable
//!    counting sort by tile then leaves every tile's list in depth order without sorting tiles
//!    (chunks of splats count their pairs per tile with 2D difference arrays, then write in
//!    parallel, each at its own offsets). The (tile, splat) pairs are built for a band of
//!    consecutive tiles at a time, sized so that the pair buffer stays under [`PAIR_BUDGET`]
//!    entries: a million screen-filling Gaussians cost time, not unbounded memory.
//! 3. **Blend** each tile (tiles in parallel): per splat and row, only the pixels of the row that
//!    its ellipse can reach are visited; a pixel composites front to back and stops at the
//!    transmittance floor; a tile stops when all its pixels have.
//!
//! Per-pixel work is in f32, on pixel offsets from the splat's centre that are exact wherever the
//! splat sits in the image (its centre is stored relative to its box's corner).

use std::ops::Range;
use std::sync::Arc;
use std::sync::atomic::{AtomicU32, Ordering};

use glam::{DMat3, DQuat, DVec3};
use rayon::prelude::*;

use super::{
    ALPHA_MAX, ALPHA_MIN, EPS2D, FOV_CLAMP, FeatureImage, Image, Rasterizer, RenderOptions,
    SIGMA_EXTENT, TRANSMITTANCE_MIN,
};
use crate::{Camera, GaussianSet, RendererError};

/// Tile edge in pixels.
pub const TILE: u32 = 16;
/// Most (tile, splat) pairs held at once; more are processed in successive bands of tiles.
pub const PAIR_BUDGET: usize = 1 << 24;

/// Renders on the CPU with rayon.
#[derive(Debug, Clone)]
pub struct CpuRasterizer {
    /// `None`: rayon's global pool (all cores).
    pool: Option<Arc<rayon::ThreadPool>>,
    pair_budget: usize,
}

impl Default for CpuRasterizer {
    fn default() -> Self {
        Self {
            pool: None,
            pair_budget: PAIR_BUDGET,
        }
    }
}

impl CpuRasterizer {
    /// A rasterizer on rayon's global pool (as many threads as cores, unless `RAYON_NUM_THREADS`
    /// says otherwise).
    pub fn new() -> Self {
        Self::default()
    }

    /// Holds at most `pairs` (tile, Gaussian) pairs (4 bytes each) at once, binning bands of
    /// tiles in turn; [`PAIR_BUDGET`] by default. Changes memory and time, never the image.
    pub fn with_pair_budget(mut self, pairs: usize) -> Self {
        self.pair_budget = pairs.max(1);
        self
    }

    /// A rasterizer with its own pool of `threads` threads (0: as many as cores).
    pub fn with_threads(threads: usize) -> Result<Self, RendererError> {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .thread_name(|i| format!("c4g-raster-{i}"))
            .build()
            .map_err(|e| RendererError::ThreadPool(e.to_string()))?;
        Ok(Self {
            pool: Some(Arc::new(pool)),
            ..Self::default()
        })
    }

    /// Threads this rasterizer renders with.
    pub fn threads(&self) -> usize {
        self.pool
            .as_ref()
            .map_or_else(rayon::current_num_threads, |p| p.current_num_threads())
    }
}

impl Rasterizer for CpuRasterizer {
    fn render(
        &self,
        gaussians: &GaussianSet,
        camera: &Camera,
        options: &RenderOptions,
    ) -> Result<Image, RendererError> {
        options.validate()?;
        if u32::try_from(gaussians.len()).is_err() {
            return Err(RendererError::InvalidRenderOptions(format!(
                "{} Gaussians are more than one render can index",
                gaussians.len()
            )));
        }
        let job = || render_frame(gaussians, camera, options, self.pair_budget);
        Ok(match &self.pool {
            Some(pool) => pool.install(job),
            None => job(),
        })
    }
}

/// A Gaussian as the pixels see it.
#[derive(Debug, Clone, Copy)]
struct Splat {
    /// Pixel coordinates of the centre relative to the box corner `(x0, y0)`: pixel offsets are
    /// then exact in f32 however far from the image origin the box is.
    u: f32,
    v: f32,
    /// The Mahalanobis distance in the form `d² = a·(dx − k·dy)² + dy²·inv_syy`, a sum of two
    /// non-negative terms (no cancellation however thin the ellipse): with Σ2D =
    /// `[[sxx, sxy], [sxy, syy]]`, `a = syy / det`, `k = sxy / syy`, `inv_syy = 1 / syy`.
    a: f32,
    k: f32,
    inv_syy: f32,
    /// Squared reach: `d²` beyond this cannot contribute (3 sigma, or less for faint splats).
    reach2: f32,
    opacity: f32,
    depth: f32,
    color: [f32; 3],
    /// Index in the Gaussian set.
    index: u32,
    /// Inclusive pixel box, inside the image.
    x0: u32,
    y0: u32,
    x1: u32,
    y1: u32,
}

impl Splat {
    fn tiles(&self) -> (u32, u32, u32, u32) {
        (
            self.x0 / TILE,
            self.y0 / TILE,
            self.x1 / TILE,
            self.y1 / TILE,
        )
    }
}

/// What projection needs of the camera, in f64.
struct View {
    rotation: DMat3,
    translation: DVec3,
    fx: f64,
    fy: f64,
    cx: f64,
    cy: f64,
    lim_x: f64,
    lim_y: f64,
    near: f64,
    far: f64,
    width: u32,
    height: u32,
}

impl View {
    fn new(camera: &Camera, options: &RenderOptions) -> Self {
        let pose = camera.world_to_camera();
        let k = camera.intrinsics();
        let (fx, fy) = (f64::from(k.fx), f64::from(k.fy));
        let fov_clamp = f64::from(FOV_CLAMP);
        Self {
            rotation: DMat3::from_cols(
                pose.matrix3.x_axis.as_dvec3(),
                pose.matrix3.y_axis.as_dvec3(),
                pose.matrix3.z_axis.as_dvec3(),
            ),
            translation: pose.translation.as_dvec3(),
            fx,
            fy,
            cx: f64::from(k.cx),
            cy: f64::from(k.cy),
            lim_x: fov_clamp * f64::from(k.width) / (2.0 * fx),
            lim_y: fov_clamp * f64::from(k.height) / (2.0 * fy),
            near: f64::from(options.near),
            far: f64::from(options.far),
            width: k.width,
            height: k.height,
        }
    }

    /// The splat of Gaussian `i`, or `None` when it is skipped or reaches no pixel.
    fn project(&self, set: &GaussianSet, i: usize) -> Option<Splat> {
        let finite = |v: &[f32]| v.iter().all(|x| x.is_finite());
        let (p, s, q, o, c) = (
            &set.positions()[i],
            &set.scales()[i],
            &set.rotations()[i],
            set.opacities()[i],
            &set.colors()[i],
        );
        let features_ok = set.features().and_then(|f| f.row(i)).is_none_or(finite);
        if !(finite(p) && finite(s) && finite(q) && o.is_finite() && finite(c) && features_ok) {
            return None;
        }
        // Alpha never exceeds the opacity: a Gaussian this faint reaches no pixel.
        if o < ALPHA_MIN {
            return None;
        }
        let q = DQuat::from_xyzw(q[1].into(), q[2].into(), q[3].into(), q[0].into());
        let norm = q.length();
        if norm == 0.0 {
            return None;
        }
        let p_cam =
            self.rotation * DVec3::new(p[0].into(), p[1].into(), p[2].into()) + self.translation;
        let z = p_cam.z;
        if !(z >= self.near && z <= self.far) {
            return None;
        }

        // EWA: Σ2D = M Mᵀ + EPS2D·I with M = J W R S (2×3). Through M the covariance is positive
        // semi-definite by construction, and its determinant is |m0 × m1|² (Cauchy–Binet) with no
        // cancellation, even for a zero scale or a needle seen end on.
        let tx = (p_cam.x / z).clamp(-self.lim_x, self.lim_x) * z;
        let ty = (p_cam.y / z).clamp(-self.lim_y, self.lim_y) * z;
        let j0 = DVec3::new(self.fx / z, 0.0, -self.fx * tx / (z * z));
        let j1 = DVec3::new(0.0, self.fy / z, -self.fy * ty / (z * z));
        let rs = DMat3::from_quat(q / norm)
            * DMat3::from_diagonal(DVec3::new(s[0].into(), s[1].into(), s[2].into()));
        let wrs = self.rotation * rs;
        // Row r of J·W·R·S is (J·W·R·S)ᵀ's column r = (W R S)ᵀ j_r.
        let m0 = wrs.transpose() * j0;
        let m1 = wrs.transpose() * j1;
        let eps = f64::from(EPS2D);
        let (mxx, myy) = (m0.length_squared(), m1.length_squared());
        let sxx = mxx + eps;
        let sxy = m0.dot(m1);
        let syy = myy + eps;
        let det = m0.cross(m1).length_squared() + eps * (mxx + myy) + eps * eps;
        if !(det.is_finite() && det > 0.0) {
            return None;
        }
        // syy ≥ EPS2D and the Schur complement det / syy ≥ EPS2D: all three are finite.
        let (a, k, inv_syy) = ((syy / det) as f32, (sxy / syy) as f32, (1.0 / syy) as f32);
        if !(a.is_finite() && k.is_finite() && inv_syy.is_finite()) {
            return None;
        }

        let u = self.fx * p_cam.x / z + self.cx;
        let v = self.fy * p_cam.y / z + self.cy;
        // Pixels can be reached only where d² ≤ 9 and opacity · exp(-d²/2) ≥ 1/255; along x the
        // ellipse d² ≤ r² spans u ± r·√Σxx (and likewise along y).
        let reach2 = f64::from(SIGMA_EXTENT * SIGMA_EXTENT)
            .min(2.0 * (f64::from(o) / f64::from(ALPHA_MIN)).ln());
        let extent = reach2.sqrt();
        let (x0, x1) = pixel_span(u, extent * sxx.sqrt(), self.width)?;
        let (y0, y1) = pixel_span(v, extent * syy.sqrt(), self.height)?;
        Some(Splat {
            u: (u - f64::from(x0)) as f32,
            v: (v - f64::from(y0)) as f32,
            a,
            k,
            inv_syy,
            reach2: reach2 as f32,
            opacity: o,
            depth: z as f32,
            color: *c,
            index: i as u32,
            x0,
            y0,
            x1,
            y1,
        })
    }
}

/// Pixels `i` (inclusive range, inside `0..size`) whose centre `i + 0.5` may lie within `radius` of
/// `centre`, with a pixel of slack for the f32 test that decides; `None` when there are none.
fn pixel_span(centre: f64, radius: f64, size: u32) -> Option<(u32, u32)> {
    let lo = (centre - radius - 0.5).floor() - 1.0;
    let hi = (centre + radius - 0.5).ceil() + 1.0;
    if !(lo.is_finite() && hi.is_finite()) || hi < 0.0 || lo > f64::from(size - 1) {
        return None;
    }
    // Both are within [0, size - 1] after clamping, so the casts are exact.
    Some((lo.max(0.0) as u32, hi.min(f64::from(size - 1)) as u32))
}

/// The whole render on the current rayon pool.
fn render_frame(
    set: &GaussianSet,
    camera: &Camera,
    options: &RenderOptions,
    pair_budget: usize,
) -> Image {
    let view = View::new(camera, options);
    let mut splats: Vec<Splat> = (0..set.len())
        .into_par_iter()
        .filter_map(|i| view.project(set, i))
        .collect();
    // Depth is ≥ near > 0, so its bit pattern orders like its value.
    splats.par_sort_unstable_by_key(|s| (u64::from(s.depth.to_bits()) << 32) | u64::from(s.index));

    let features = set.features().filter(|_| options.features);
    let channels = features.map_or(0, |f| f.width());
    let grid = TileGrid::new(view.width, view.height);
    let chunks = Chunks::count(&grid, &splats);
    let mut image = Image {
        width: view.width,
        height: view.height,
        rgb: vec![0.0; grid.pixels() * 3],
        alpha: vec![0.0; grid.pixels()],
        depth: vec![0.0; grid.pixels()],
        expected_depth: vec![0.0; grid.pixels()],
        features: (channels > 0).then(|| FeatureImage {
            channels,
            values: vec![0.0; grid.pixels() * channels],
        }),
    };
    let mut rows = TileRow::split(&grid, &mut image);
    for band in grid.bands(&chunks.totals, pair_budget) {
        let pairs = chunks.fill_band(&grid, &splats, band.clone());
        let (first, last) = (band.start / grid.tiles_x, (band.end - 1) / grid.tiles_x);
        rows[first..=last].par_iter_mut().for_each(|row| {
            let mut acc = TileAcc::new(channels);
            let tiles = (row.index * grid.tiles_x).max(band.start)
                ..((row.index + 1) * grid.tiles_x).min(band.end);
            for t in tiles {
                let k = t - band.start;
                acc.clear();
                blend_tile(
                    &mut acc,
                    &grid,
                    t,
                    &pairs.splats[pairs.offsets[k]..pairs.offsets[k + 1]],
                    &splats,
                    features.map(|f| (f.width(), f.values())),
                );
                row.write(&grid, t, &acc, options.background);
            }
        });
    }
    image
}

/// The planes of one row of tiles (`TILE` pixel rows), for one task to write.
struct TileRow<'a> {
    index: usize,
    rgb: &'a mut [f32],
    alpha: &'a mut [f32],
    depth: &'a mut [f32],
    expected_depth: &'a mut [f32],
    features: Option<(usize, &'a mut [f32])>,
}

impl<'a> TileRow<'a> {
    fn split(grid: &TileGrid, image: &'a mut Image) -> Vec<Self> {
        let px = grid.width as usize * TILE as usize;
        let mut features: Vec<Option<(usize, &mut [f32])>> = match &mut image.features {
            Some(f) => {
                let c = f.channels;
                f.values.chunks_mut(px * c).map(|v| Some((c, v))).collect()
            }
            None => (0..grid.tiles_y).map(|_| None).collect(),
        };
        image
            .rgb
            .chunks_mut(px * 3)
            .zip(image.alpha.chunks_mut(px))
            .zip(image.depth.chunks_mut(px))
            .zip(image.expected_depth.chunks_mut(px))
            .zip(features.drain(..))
            .enumerate()
            .map(
                |(index, ((((rgb, alpha), depth), expected_depth), features))| Self {
                    index,
                    rgb,
                    alpha,
                    depth,
                    expected_depth,
                    features,
                },
            )
            .collect()
    }

    /// Writes tile `t` (in this row) from its accumulations, the background under what remains.
    fn write(&mut self, grid: &TileGrid, t: usize, acc: &TileAcc, background: [f32; 3]) {
        let (x0, _, w, h) = grid.rect(t);
        let width = grid.width as usize;
        for ly in 0..h as usize {
            for lx in 0..w as usize {
                let p = ly * TILE as usize + lx;
                let q = ly * width + x0 as usize + lx;
                let transmittance = acc.transmittance[p];
                for ((out, colour), b) in self.rgb[3 * q..3 * q + 3]
                    .iter_mut()
                    .zip(acc.rgb[p])
                    .zip(background)
                {
                    *out = colour + transmittance * b;
                }
                let alpha = 1.0 - transmittance;
                self.alpha[q] = alpha;
                self.depth[q] = acc.depth[p];
                self.expected_depth[q] = if alpha > 0.0 {
                    acc.depth[p] / alpha
                } else {
                    0.0
                };
                if let Some((c, values)) = &mut self.features {
                    values[q * *c..(q + 1) * *c]
                        .copy_from_slice(&acc.features[p * *c..(p + 1) * *c]);
                }
            }
        }
    }
}

/// The image cut into tiles, row-major.
struct TileGrid {
    width: u32,
    height: u32,
    tiles_x: usize,
    tiles_y: usize,
}

impl TileGrid {
    fn new(width: u32, height: u32) -> Self {
        Self {
            width,
            height,
            tiles_x: width.div_ceil(TILE) as usize,
            tiles_y: height.div_ceil(TILE) as usize,
        }
    }

    fn len(&self) -> usize {
        self.tiles_x * self.tiles_y
    }

    fn pixels(&self) -> usize {
        self.width as usize * self.height as usize
    }

    /// Splats per tile, from a 2D difference array: O(splats + tiles), whatever the splat sizes.
    fn pair_counts(&self, splats: &[Splat]) -> Vec<usize> {
        let stride = self.tiles_x + 1;
        let mut diff = vec![0i64; stride * (self.tiles_y + 1)];
        for s in splats {
            let (tx0, ty0, tx1, ty1) = s.tiles();
            let (tx0, ty0, tx1, ty1) = (
                tx0 as usize,
                ty0 as usize,
                tx1 as usize + 1,
                ty1 as usize + 1,
            );
            diff[ty0 * stride + tx0] += 1;
            diff[ty0 * stride + tx1] -= 1;
            diff[ty1 * stride + tx0] -= 1;
            diff[ty1 * stride + tx1] += 1;
        }
        let mut counts = vec![0usize; self.len()];
        let mut above = vec![0i64; self.tiles_x];
        for ty in 0..self.tiles_y {
            let mut run = 0i64;
            for tx in 0..self.tiles_x {
                run += diff[ty * stride + tx];
                above[tx] += run;
                // A count of splats, so never negative.
                counts[ty * self.tiles_x + tx] = above[tx].max(0) as usize;
            }
        }
        counts
    }

    /// Consecutive tile ranges, each holding at most `budget` pairs (or a single tile).
    fn bands(&self, counts: &[usize], budget: usize) -> Vec<Range<usize>> {
        let mut bands = Vec::new();
        let (mut start, mut held) = (0, 0usize);
        for (t, &n) in counts.iter().enumerate() {
            if t > start && held + n > budget {
                bands.push(start..t);
                (start, held) = (t, 0);
            }
            held += n;
        }
        if start < counts.len() {
            bands.push(start..counts.len());
        }
        bands
    }

    /// Pixel rectangle of tile `t`: (x0, y0, width, height).
    fn rect(&self, t: usize) -> (u32, u32, u32, u32) {
        let (tx, ty) = ((t % self.tiles_x) as u32, (t / self.tiles_x) as u32);
        let (x0, y0) = (tx * TILE, ty * TILE);
        (
            x0,
            y0,
            TILE.min(self.width - x0),
            TILE.min(self.height - y0),
        )
    }
}

/// The depth-sorted splats cut into consecutive chunks, with each chunk's pairs per tile, so
/// that the chunks can write their pairs in parallel, each at its own offset in every tile's list:
/// the lists come out in depth order without a lock or a sort.
struct Chunks {
    len: usize,
    /// `counts[c][t]`: pairs of chunk `c` in tile `t`.
    counts: Vec<Vec<usize>>,
    /// Pairs per tile, all chunks.
    totals: Vec<usize>,
}

/// The (tile, splat) pairs of one band of tiles: tile `band.start + k` holds
/// `splats[offsets[k]..offsets[k + 1]]`, indices into the depth-sorted splats.
struct BandPairs {
    offsets: Vec<usize>,
    splats: Vec<u32>,
}

impl Chunks {
    fn count(grid: &TileGrid, splats: &[Splat]) -> Self {
        let len = splats
            .len()
            .div_ceil(4 * rayon::current_num_threads())
            .max(1 << 14);
        let counts: Vec<Vec<usize>> = splats
            .par_chunks(len)
            .map(|chunk| grid.pair_counts(chunk))
            .collect();
        let mut totals = vec![0usize; grid.len()];
        for c in &counts {
            for (total, n) in totals.iter_mut().zip(c) {
                *total += n;
            }
        }
        Self {
            len,
            counts,
            totals,
        }
    }

    /// The pairs of `band`, each tile's list in the splats' (depth) order: a stable counting sort
    /// whose chunks write in parallel.
    fn fill_band(&self, grid: &TileGrid, splats: &[Splat], band: Range<usize>) -> BandPairs {
        let mut offsets = Vec::with_capacity(band.len() + 1);
        offsets.push(0);
        for &n in &self.totals[band.clone()] {
            offsets.push(offsets[offsets.len() - 1] + n);
        }
        // Where chunk c starts writing in each tile of the band.
        let mut starts = Vec::with_capacity(self.counts.len());
        let mut next = offsets[..band.len()].to_vec();
        for c in &self.counts {
            starts.push(next.clone());
            for (cursor, n) in next.iter_mut().zip(&c[band.clone()]) {
                *cursor += n;
            }
        }
        let out: Vec<AtomicU32> = (0..offsets[band.len()])
            .into_par_iter()
            .map(|_| AtomicU32::new(0))
            .collect();
        let (row_first, row_last) = (band.start / grid.tiles_x, (band.end - 1) / grid.tiles_x);
        splats
            .par_chunks(self.len)
            .zip(starts)
            .enumerate()
            .for_each(|(c, (chunk, mut cursor))| {
                for (j, s) in chunk.iter().enumerate() {
                    let k = (c * self.len + j) as u32;
                    let (tx0, ty0, tx1, ty1) = s.tiles();
                    for ty in (ty0 as usize).max(row_first)..=(ty1 as usize).min(row_last) {
                        let row_start = ty * grid.tiles_x;
                        let lo = (row_start + tx0 as usize).max(band.start);
                        let hi = (row_start + tx1 as usize + 1).min(band.end);
                        for t in lo..hi {
                            let slot = &mut cursor[t - band.start];
                            // Every slot is written by exactly one chunk: no ordering needed.
                            out[*slot].store(k, Ordering::Relaxed);
                            *slot += 1;
                        }
                    }
                }
            });
        BandPairs {
            offsets,
            splats: out.into_iter().map(AtomicU32::into_inner).collect(),
        }
    }
}

/// Pixels in a tile.
const TILE_PIXELS: usize = (TILE * TILE) as usize;

/// The accumulations of one tile, pixel `(x, y)` of the tile at `y · TILE + x` (edge tiles use
/// only part of it).
struct TileAcc {
    rgb: [[f32; 3]; TILE_PIXELS],
    transmittance: [f32; TILE_PIXELS],
    depth: [f32; TILE_PIXELS],
    features: Vec<f32>,
}

impl TileAcc {
    fn new(channels: usize) -> Self {
        Self {
            rgb: [[0.0; 3]; TILE_PIXELS],
            transmittance: [1.0; TILE_PIXELS],
            depth: [0.0; TILE_PIXELS],
            features: vec![0.0; TILE_PIXELS * channels],
        }
    }

    fn clear(&mut self) {
        self.rgb = [[0.0; 3]; TILE_PIXELS];
        self.transmittance = [1.0; TILE_PIXELS];
        self.depth = [0.0; TILE_PIXELS];
        self.features.fill(0.0);
    }
}

/// Composites `list` (indices into `splats`, front to back) over the pixels of tile `t`.
fn blend_tile(
    out: &mut TileAcc,
    grid: &TileGrid,
    t: usize,
    list: &[u32],
    splats: &[Splat],
    features: Option<(usize, &[f32])>,
) {
    let (x0, y0, w, h) = grid.rect(t);
    let channels = features.map_or(0, |(c, _)| c);
    let mut done = [false; TILE_PIXELS];
    let mut live = (w * h) as usize;
    let cut = SIGMA_EXTENT * SIGMA_EXTENT;
    for &index in list {
        let s = &splats[index as usize];
        let feature_row = features.map(|(c, values)| {
            let start = s.index as usize * c;
            &values[start..start + c]
        });
        // The rows' culls are exact-math bounds of `d² ≤ reach2`, widened for f32 rounding;
        // the test below decides.
        let reach2 = s.reach2 * 1.001 + 1e-3;
        for py in s.y0.max(y0)..=s.y1.min(y0 + h - 1) {
            let dy = (py - s.y0) as f32 + 0.5 - s.v;
            let row_d2 = dy * dy * s.inv_syy;
            if row_d2 > reach2 {
                continue;
            }
            // On this row d² = a·(dx − centre)² + row_d2: within `half` of `centre`.
            let centre = s.k * dy;
            let half = ((reach2 - row_d2) / s.a).sqrt();
            // Offsets from the box corner of the first and last pixel centres within reach
            // (infinite when `a` underflows for a huge splat: then the whole box row).
            let first = (centre - half + s.u - 0.5).floor() - 1.0;
            let last = (centre + half + s.u - 0.5).ceil() + 1.0;
            let lo = s.x0 + first.max(0.0).min((s.x1 - s.x0) as f32) as u32;
            let hi = s.x0 + last.max(0.0).min((s.x1 - s.x0) as f32) as u32;
            let row = ((py - y0) * TILE) as usize;
            for px in lo.max(x0)..=hi.min(x0 + w - 1) {
                // Below TILE_PIXELS by construction; the mask lets the compiler see it.
                let p = (row + (px - x0) as usize) & (TILE_PIXELS - 1);
                if done[p] {
                    continue;
                }
                let e = (px - s.x0) as f32 + 0.5 - s.u - centre;
                let d2 = s.a * e * e + row_d2;
                if d2 > cut {
                    continue;
                }
                let alpha = (s.opacity * (-0.5 * d2).exp()).min(ALPHA_MAX);
                if alpha < ALPHA_MIN {
                    continue;
                }
                let t_now = out.transmittance[p];
                let t_next = t_now * (1.0 - alpha);
                if t_next < TRANSMITTANCE_MIN {
                    done[p] = true;
                    live -= 1;
                    continue;
                }
                let weight = alpha * t_now;
                for (acc, c) in out.rgb[p].iter_mut().zip(s.color) {
                    *acc += weight * c;
                }
                out.depth[p] += weight * s.depth;
                if let Some(row) = feature_row {
                    for (acc, f) in out.features[p * channels..(p + 1) * channels]
                        .iter_mut()
                        .zip(row)
                    {
                        *acc += weight * f;
                    }
                }
                out.transmittance[p] = t_next;
            }
        }
        if live == 0 {
            break;
        }
    }
}
