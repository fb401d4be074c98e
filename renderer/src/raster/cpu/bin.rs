//! Stage 2, binning: the image's grid of `TILE`-pixel tiles, how many splats reach each tile, the
//! bands of tiles whose (tile, splat) pairs fit the pair budget, and the parallel stable counting
//! sort that writes a band's pairs with every tile's list in depth order. Apart from projection
//! and blending because it is bookkeeping over splat boxes: it never computes a pixel value.

use std::ops::Range;
use std::sync::atomic::{AtomicU32, Ordering};

use rayon::prelude::*;

use super::project::Splat;
use super::tiling::TILE;

/// The image cut into tiles, row-major.
pub(super) struct TileGrid {
    pub(super) width: u32,
    pub(super) height: u32,
    pub(super) tiles_x: usize,
    pub(super) tiles_y: usize,
}

impl TileGrid {
    pub(super) fn new(width: u32, height: u32) -> Self {
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

    pub(super) fn pixels(&self) -> usize {
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
    pub(super) fn bands(&self, counts: &[usize], budget: usize) -> Vec<Range<usize>> {
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
    pub(super) fn rect(&self, t: usize) -> (u32, u32, u32, u32) {
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
pub(super) struct Chunks {
    len: usize,
    /// `counts[c][t]`: pairs of chunk `c` in tile `t`.
    counts: Vec<Vec<usize>>,
    /// Pairs per tile, all chunks.
    pub(super) totals: Vec<usize>,
}

/// The (tile, splat) pairs of one band of tiles: tile `band.start + k` holds
/// `splats[offsets[k]..offsets[k + 1]]`, indices into the depth-sorted splats.
pub(super) struct BandPairs {
    pub(super) offsets: Vec<usize>,
    pub(super) splats: Vec<u32>,
}

impl Chunks {
    pub(super) fn count(grid: &TileGrid, splats: &[Splat]) -> Self {
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
    pub(super) fn fill_band(
        &self,
        grid: &TileGrid,
        splats: &[Splat],
        band: Range<usize>,
    ) -> BandPairs {
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
