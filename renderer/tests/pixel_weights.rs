//! Per-pixel weights (`CpuRasterizer::pixel_weights`) against the render they claim to explain,
//! at every pixel of small random scenes, with both footprints:
//! - they sum to the rendered alpha and, times each Gaussian's depth, to the rendered
//!   alpha-weighted depth: 1e-5 absolute (alpha and depth are accumulated in the same order with
//!   the same f32 arithmetic; alpha is 1 − T in the render and a sum here, which round apart by a
//!   few ulps of 1);
//! - they are front to back, positive, and each at most ALPHA_MAX;
//! - a pixel outside the image, or with nothing on it, has none.
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use c4g_renderer::raster::ALPHA_MAX;
use c4g_renderer::{CpuRasterizer, Rasterizer, RenderOptions};
use c4g_scene::Footprint;
use common::*;

#[test]
fn weights_sum_to_the_rendered_alpha_and_depth_at_every_pixel() {
    let rasterizer = CpuRasterizer::new();
    let (w, h) = (48u32, 32u32);
    let camera = camera(w, h, 40.0);
    let pixels: Vec<(u32, u32)> = (0..h).flat_map(|y| (0..w).map(move |x| (x, y))).collect();
    for footprint in [Footprint::Ellipse, Footprint::Tiles3dgs] {
        let options = RenderOptions {
            footprint,
            ..RenderOptions::default()
        };
        for seed in 0..3 {
            let set = random_set(150, seed, 1.0, 0.1);
            let image = rasterizer.render(&set, &camera, &options).unwrap();
            let weights = rasterizer
                .pixel_weights(&set, &camera, &options, &pixels)
                .unwrap();
            let mut covered = 0;
            for (p, list) in weights.iter().enumerate() {
                let alpha: f32 = list.iter().map(|g| g.weight).sum();
                let depth: f32 = list.iter().map(|g| g.weight * g.depth).sum();
                let what = format!("{footprint:?} seed {seed} pixel {p}");
                assert!(
                    (alpha - image.alpha[p]).abs() <= 1e-5,
                    "{what}: {alpha} vs {}",
                    image.alpha[p]
                );
                assert!(
                    (depth - image.depth[p]).abs() <= 1e-5 * image.depth[p].max(1.0),
                    "{what}: depth"
                );
                assert!(
                    list.windows(2).all(|g| g[0].depth <= g[1].depth),
                    "{what}: order"
                );
                assert!(
                    list.iter().all(|g| g.weight > 0.0 && g.weight <= ALPHA_MAX),
                    "{what}"
                );
                covered += usize::from(!list.is_empty());
            }
            assert!(
                covered > pixels.len() / 4,
                "the scene covers too little to test: {covered}"
            );
        }
    }
}

#[test]
fn pixels_off_the_image_or_the_scene_have_no_weights() {
    let rasterizer = CpuRasterizer::new();
    let camera = camera(32, 32, 30.0);
    let set = random_set(20, 7, 1.0, 0.02);
    let options = RenderOptions::default();
    let image = rasterizer.render(&set, &camera, &options).unwrap();
    let empty = (0..32 * 32).find(|&p| image.alpha[p] == 0.0).unwrap() as u32;
    let weights = rasterizer
        .pixel_weights(
            &set,
            &camera,
            &options,
            &[(500, 3), (empty % 32, empty / 32)],
        )
        .unwrap();
    assert!(weights.iter().all(Vec::is_empty), "{weights:?}");
}
