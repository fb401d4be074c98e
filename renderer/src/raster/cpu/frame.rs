//! One frame of a render: its projection, depth order and tile pairs ([`Frame`]), and the
//! blending stage over them: where the forward and the backward pass both start.

use rayon::prelude::*;

use c4g_scene::{Camera, GaussianSet};

use super::bin::{Chunks, TileGrid};
use super::blend::{TileAcc, TileRow, blend_tile, d2_cut};
use super::project::{Splat, View};
use crate::raster::{FeatureImage, Image, RenderOptions};

/// One frame's projection, depth order and pair counts: where the forward and the backward pass
/// both start.
pub(super) struct Frame {
    pub(super) view: View,
    /// The splats that reach a pixel, sorted by (depth, index).
    pub(super) splats: Vec<Splat>,
    pub(super) grid: TileGrid,
    pub(super) chunks: Chunks,
}

impl Frame {
    /// Projects every Gaussian of `set`, sorts the splats front to back and counts their tiles.
    pub(super) fn new(set: &GaussianSet, camera: &Camera, options: &RenderOptions) -> Self {
        let view = View::new(camera, options);
        let mut splats: Vec<Splat> = (0..set.len())
            .into_par_iter()
            .filter_map(|i| view.project(set, i))
            .collect();
        // Depth is ≥ near > 0, so its bit pattern orders like its value.
        splats.par_sort_unstable_by_key(|s| {
            (u64::from(s.depth.to_bits()) << 32) | u64::from(s.index)
        });
        let grid = TileGrid::new(view.width, view.height);
        let chunks = Chunks::count(&grid, &splats);
        Self {
            view,
            splats,
            grid,
            chunks,
        }
    }
}

/// One render, and with `contributions` every Gaussian's blending weight summed over the image's
/// pixels (Σ transmittance · alpha; 0 for a Gaussian that reaches no pixel).
pub(super) fn render_frame(
    set: &GaussianSet,
    camera: &Camera,
    options: &RenderOptions,
    pair_budget: usize,
    contributions: bool,
) -> (Image, Option<Vec<f32>>) {
    let frame = Frame::new(set, camera, options);
    blend_frame(&frame, set, options, pair_budget, contributions, None)
}

/// The blending stage of a render of `frame`; with `saved`, each pixel's final transmittance and
/// one past the list position of its last composited splat are written there (for the backward
/// pass).
pub(super) fn blend_frame(
    frame: &Frame,
    set: &GaussianSet,
    options: &RenderOptions,
    pair_budget: usize,
    contributions: bool,
    saved: Option<(&mut [f32], &mut [u32])>,
) -> (Image, Option<Vec<f32>>) {
    let Frame {
        view,
        splats,
        grid,
        chunks,
    } = frame;
    let features = set.features().filter(|_| options.features);
    let channels = features.map_or(0, |f| f.width());
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
    let mut rows = TileRow::split(grid, &mut image, saved);
    let cut = d2_cut(options.footprint);
    let mut sums = contributions.then(|| vec![0.0f32; set.len()]);
    for band in grid.bands(&chunks.totals, pair_budget) {
        let pairs = chunks.fill_band(grid, splats, band.clone());
        let (first, last) = (band.start / grid.tiles_x, (band.end - 1) / grid.tiles_x);
        let partial: Vec<Vec<(u32, f32)>> = rows[first..=last]
            .par_iter_mut()
            .map(|row| {
                let mut acc = TileAcc::new(channels);
                let mut local = Vec::new();
                let tiles = (row.index * grid.tiles_x).max(band.start)
                    ..((row.index + 1) * grid.tiles_x).min(band.end);
                for t in tiles {
                    let k = t - band.start;
                    acc.clear();
                    blend_tile(
                        &mut acc,
                        grid,
                        t,
                        &pairs.splats[pairs.offsets[k]..pairs.offsets[k + 1]],
                        splats,
                        features.map(|f| (f.width(), f.values())),
                        cut,
                        contributions.then_some(&mut local),
                    );
                    row.write(grid, t, &acc, options.background);
                }
                local
            })
            .collect();
        if let Some(sums) = &mut sums {
            for (index, value) in partial.into_iter().flatten() {
                sums[index as usize] += value;
            }
        }
    }
    (image, sums)
}
