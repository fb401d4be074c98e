//! Stage 3, blending: a tile's front-to-back compositing of its depth-ordered splats into a
//! tile-sized accumulator, and the rows of tiles that write those accumulations (over the
//! background) into the image's planes. Apart from projection and binning because it is the
//! per-pixel f32 loop, where the forward model's alpha and transmittance rules live.

use super::bin::TileGrid;
use super::project::Splat;
use super::tiling::TILE;
use crate::raster::{ALPHA_MAX, ALPHA_MIN, Image, SIGMA_EXTENT, TRANSMITTANCE_MIN};
use c4g_scene::Footprint;

/// The planes of one row of tiles (`TILE` pixel rows), for one task to write.
pub(super) struct TileRow<'a> {
    pub(super) index: usize,
    rgb: &'a mut [f32],
    alpha: &'a mut [f32],
    depth: &'a mut [f32],
    expected_depth: &'a mut [f32],
    features: Option<(usize, &'a mut [f32])>,
    /// What the backward pass needs per pixel, when it is kept: the final transmittance and one
    /// past the list position of the last splat composited there.
    saved: Option<(&'a mut [f32], &'a mut [u32])>,
}

impl<'a> TileRow<'a> {
    pub(super) fn split(
        grid: &TileGrid,
        image: &'a mut Image,
        saved: Option<(&'a mut [f32], &'a mut [u32])>,
    ) -> Vec<Self> {
        let px = grid.width as usize * TILE as usize;
        let mut saved: Vec<Option<(&mut [f32], &mut [u32])>> = match saved {
            Some((t, last)) => t
                .chunks_mut(px)
                .zip(last.chunks_mut(px))
                .map(Some)
                .collect(),
            None => (0..grid.tiles_y).map(|_| None).collect(),
        };
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
            .zip(saved.drain(..))
            .enumerate()
            .map(
                |(index, (((((rgb, alpha), depth), expected_depth), features), saved))| Self {
                    index,
                    rgb,
                    alpha,
                    depth,
                    expected_depth,
                    features,
                    saved,
                },
            )
            .collect()
    }

    /// Writes tile `t` (in this row) from its accumulations, the background under what remains.
    pub(super) fn write(&mut self, grid: &TileGrid, t: usize, acc: &TileAcc, background: [f32; 3]) {
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
                if let Some((final_t, last)) = &mut self.saved {
                    final_t[q] = transmittance;
                    last[q] = acc.last[p];
                }
            }
        }
    }
}

/// Pixels in a tile.
const TILE_PIXELS: usize = (TILE * TILE) as usize;

/// The accumulations of one tile, pixel `(x, y)` of the tile at `y · TILE + x` (edge tiles use
/// only part of it).
pub(super) struct TileAcc {
    rgb: [[f32; 3]; TILE_PIXELS],
    transmittance: [f32; TILE_PIXELS],
    depth: [f32; TILE_PIXELS],
    /// One past the position in the tile's list of the last splat composited at each pixel (0:
    /// none): where the backward pass starts its walk back.
    last: [u32; TILE_PIXELS],
    features: Vec<f32>,
}

impl TileAcc {
    pub(super) fn new(channels: usize) -> Self {
        Self {
            rgb: [[0.0; 3]; TILE_PIXELS],
            transmittance: [1.0; TILE_PIXELS],
            depth: [0.0; TILE_PIXELS],
            last: [0; TILE_PIXELS],
            features: vec![0.0; TILE_PIXELS * channels],
        }
    }

    pub(super) fn clear(&mut self) {
        self.rgb = [[0.0; 3]; TILE_PIXELS];
        self.transmittance = [1.0; TILE_PIXELS];
        self.depth = [0.0; TILE_PIXELS];
        self.last = [0; TILE_PIXELS];
        self.features.fill(0.0);
    }
}

/// The `d²` beyond which `footprint` evaluates no pixel: 3 sigma for the ellipse; none for the
/// 3DGS tiles, whose boxes are the tiles themselves.
pub(super) fn d2_cut(footprint: Footprint) -> f32 {
    match footprint {
        Footprint::Ellipse => SIGMA_EXTENT * SIGMA_EXTENT,
        Footprint::Tiles3dgs => f32::INFINITY,
    }
}

/// The squared reach used by the row culls: exact-math bounds of `d² ≤ reach2`, widened for f32
/// rounding; the per-pixel test decides.
#[inline(always)]
pub(super) fn widened_reach2(s: &Splat) -> f32 {
    s.reach2 * 1.001 + 1e-3
}

/// What one pixel row of a splat's box needs: its `dy`, `dy²·inv_syy`, the centre of its run
/// (`k·dy`) and the run of columns `lo..=hi` within reach (inside the box).
pub(super) struct RowReach {
    pub(super) dy: f32,
    pub(super) row_d2: f32,
    pub(super) centre: f32,
    pub(super) lo: u32,
    pub(super) hi: u32,
}

/// The columns of pixel row `py` that splat `s` can reach (`reach2` from [`widened_reach2`]), or
/// `None` when the whole row is beyond it. Shared by the forward and backward passes so that both
/// evaluate exactly the same pixels.
#[inline(always)]
pub(super) fn row_reach(s: &Splat, py: u32, reach2: f32) -> Option<RowReach> {
    let dy = (py - s.y0) as f32 + 0.5 - s.v;
    let row_d2 = dy * dy * s.inv_syy;
    if row_d2 > reach2 {
        return None;
    }
    // On this row d² = a·(dx − centre)² + row_d2: within `half` of `centre`.
    let centre = s.k * dy;
    let half = ((reach2 - row_d2) / s.a).sqrt();
    // Offsets from the box corner of the first and last pixel centres within reach (infinite
    // when `a` underflows for a huge splat: then the whole box row).
    let first = (centre - half + s.u - 0.5).floor() - 1.0;
    let last = (centre + half + s.u - 0.5).ceil() + 1.0;
    Some(RowReach {
        dy,
        row_d2,
        centre,
        lo: s.x0 + first.max(0.0).min((s.x1 - s.x0) as f32) as u32,
        hi: s.x0 + last.max(0.0).min((s.x1 - s.x0) as f32) as u32,
    })
}

/// A splat evaluated at one pixel centre of a row ([`sample`]).
pub(super) struct Sample {
    /// The pixel centre's x offset from the splat's centre.
    pub(super) dx: f32,
    /// `exp(−d²/2)`.
    pub(super) gauss: f32,
    /// `opacity · gauss`, then clamped to [`ALPHA_MAX`].
    pub(super) alpha: f32,
    /// True when the clamp decided `alpha` (`opacity · gauss > ALPHA_MAX`): its gradient is then
    /// zero. At equality the derivative is the one from below, as autograd's clamp has it.
    pub(super) clamped: bool,
}

/// Splat `s` at pixel column `px` of a row ([`row_reach`]'s `centre` and `row_d2`): `None` when
/// the footprint's `cut` or the 1/255 floor leaves the pixel out. The forward and backward passes
/// both decide through this, so they composite exactly the same (pixel, splat) pairs.
#[inline(always)]
pub(super) fn sample(s: &Splat, px: u32, centre: f32, row_d2: f32, cut: f32) -> Option<Sample> {
    let dx = (px - s.x0) as f32 + 0.5 - s.u;
    let e = dx - centre;
    // A sum of non-negative terms: 3DGS's skip where the exponent -d²/2 is positive (an f32
    // artefact of its expanded form) cannot fire here.
    let d2 = s.a * e * e + row_d2;
    if d2 > cut {
        return None;
    }
    let gauss = (-0.5 * d2).exp();
    let raw = s.opacity * gauss;
    let alpha = raw.min(ALPHA_MAX);
    if alpha < ALPHA_MIN {
        return None;
    }
    Some(Sample {
        dx,
        gauss,
        alpha,
        clamped: raw > ALPHA_MAX,
    })
}

/// Composites `list` (indices into `splats`, front to back) over the pixels of tile `t`; pixels
/// of a splat's box with `d²` above `cut` ([`d2_cut`]) are not evaluated. With `contributions`,
/// each splat's blending weights over the tile's pixels (Σ transmittance · alpha) are appended to
/// it as (Gaussian index, sum).
#[allow(clippy::too_many_arguments)]
pub(super) fn blend_tile(
    out: &mut TileAcc,
    grid: &TileGrid,
    t: usize,
    list: &[u32],
    splats: &[Splat],
    features: Option<(usize, &[f32])>,
    cut: f32,
    mut contributions: Option<&mut Vec<(u32, f32)>>,
) {
    let (x0, y0, w, h) = grid.rect(t);
    let channels = features.map_or(0, |(c, _)| c);
    let mut done = [false; TILE_PIXELS];
    let mut live = (w * h) as usize;
    for (position, &index) in list.iter().enumerate() {
        let s = &splats[index as usize];
        let feature_row = features.map(|(c, values)| {
            let start = s.index as usize * c;
            &values[start..start + c]
        });
        let reach2 = widened_reach2(s);
        let mut contribution = 0.0f32;
        for py in s.y0.max(y0)..=s.y1.min(y0 + h - 1) {
            let Some(RowReach {
                row_d2,
                centre,
                lo,
                hi,
                ..
            }) = row_reach(s, py, reach2)
            else {
                continue;
            };
            let row = ((py - y0) * TILE) as usize;
            for px in lo.max(x0)..=hi.min(x0 + w - 1) {
                // Below TILE_PIXELS by construction; the mask lets the compiler see it.
                let p = (row + (px - x0) as usize) & (TILE_PIXELS - 1);
                if done[p] {
                    continue;
                }
                let Some(Sample { alpha, .. }) = sample(s, px, centre, row_d2, cut) else {
                    continue;
                };
                let t_now = out.transmittance[p];
                let t_next = t_now * (1.0 - alpha);
                if t_next < TRANSMITTANCE_MIN {
                    done[p] = true;
                    live -= 1;
                    continue;
                }
                let weight = alpha * t_now;
                contribution += weight;
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
                out.last[p] = position as u32 + 1;
            }
        }
        if let Some(sums) = contributions.as_deref_mut()
            && contribution > 0.0
        {
            sums.push((s.index, contribution));
        }
        if live == 0 {
            break;
        }
    }
}
