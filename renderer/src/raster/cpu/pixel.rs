//! Which Gaussians make a pixel: each one's blending weight `Tᵢ · αᵢ` there, front to back.
//!
//! The same forward model as a render, evaluated at a few pixels instead of tiled over the image:
//! splats in the render's order (depth, then index), the same per-pixel arithmetic as
//! `blend_tile` (offsets from the splat's box corner, its row cull, the footprint's cut, the alpha
//! floor, the transmittance floor), so the weights sum to the rendered alpha and weight the
//! rendered depth, which the tests hold them to. What point tracking asks: the Gaussians that
//! explain a pixel, and by how much.

use super::blend::{Sample, d2_cut, row_reach, sample, widened_reach2};
use super::project::{Splat, View};
use crate::raster::{RenderOptions, TRANSMITTANCE_MIN};
use c4g_scene::{Camera, GaussianSet};

/// A Gaussian's share of a pixel.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PixelWeight {
    /// Index in the set.
    pub index: u32,
    /// Its blending weight there, `Tᵢ · αᵢ`.
    pub weight: f32,
    /// Its camera-space depth.
    pub depth: f32,
}

/// The weights at each pixel `(x, y)` (column, row; pixels outside the image have none), front
/// to back.
pub(super) fn pixel_weights(
    set: &GaussianSet,
    camera: &Camera,
    options: &RenderOptions,
    pixels: &[(u32, u32)],
) -> Vec<Vec<PixelWeight>> {
    let view = View::new(camera, options);
    let mut splats: Vec<Splat> = (0..set.len())
        .filter_map(|i| view.project(set, i))
        .collect();
    splats.sort_unstable_by_key(|s| (u64::from(s.depth.to_bits()) << 32) | u64::from(s.index));
    let cut = d2_cut(options.footprint);
    pixels
        .iter()
        .map(|&(px, py)| weights_at(&splats, px, py, cut))
        .collect()
}

fn weights_at(splats: &[Splat], px: u32, py: u32, cut: f32) -> Vec<PixelWeight> {
    let mut out = Vec::new();
    let mut transmittance = 1.0f32;
    for s in splats {
        if px < s.x0 || px > s.x1 || py < s.y0 || py > s.y1 {
            continue;
        }
        // Exactly blend_tile's decisions: its row cull and run of columns, then the same test.
        let Some(row) = row_reach(s, py, widened_reach2(s)) else {
            continue;
        };
        if px < row.lo || px > row.hi {
            continue;
        }
        let Some(Sample { alpha, .. }) = sample(s, px, row.centre, row.row_d2, cut) else {
            continue;
        };
        let next = transmittance * (1.0 - alpha);
        if next < TRANSMITTANCE_MIN {
            break;
        }
        out.push(PixelWeight {
            index: s.index,
            weight: alpha * transmittance,
            depth: s.depth,
        });
        transmittance = next;
    }
    out
}
