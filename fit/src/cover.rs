//! Covering the whole source frame before a fit: [`cover_frame`].
//!
//! The feed-forward model sees only the square centre crop of a source frame, so its Gaussians
//! cover only that; a fit supervised with the whole frame would otherwise have to grow the rest
//! from nothing (densification only clones and splits what is already there). So the uncovered
//! part of the frame gets Gaussians from the frame's own pixels: on a grid every `spacing_px`
//! pixels, wherever the start at keyframe 0 renders alpha under 0.5, one Gaussian
//! - at the depth of the nearest covered grid cell (nearest in grid steps, the chessboard
//!   distance, found by one breadth-first pass so a 1024-pixel frame costs no more than its cells;
//!   the median depth of the set in front of the camera when nothing is covered; depth 1 when
//!   nothing is in front), so the border continues the scene's geometry instead of a wall;
//! - unprojected through the pixel's centre, coloured by the mean of the frame's pixels in its
//!   cell;
//! - isotropic, with a standard deviation of one grid spacing at that depth: neighbours at
//!   opacity 0.8 then leave alpha ≥ 0.9 everywhere but the outermost corners; a thin or oriented
//!   Gaussian would be a guess the fit has to undo;
//! - the same at every keyframe and marked static: the border is background until the fit says
//!   otherwise.
//!
//! The added Gaussians carry no feature vectors, so a set that had a feature block loses it (a
//! fitted scene carries none: the fit's sets are built from its parameters).

use std::collections::VecDeque;

use c4g_renderer::{CpuRasterizer, Rasterizer, RenderOptions};
use c4g_scene::GaussianSet;
use glam::Vec3;

use crate::fit::Frame;
use crate::scene::FittedScene;

/// A grid cell is covered when the start's alpha there is at least this.
const COVERED: f32 = 0.5;
/// Opacity of an added Gaussian.
const OPACITY: f32 = 0.8;
/// Standard deviation of an added Gaussian, in grid spacings.
const SIZE: f32 = 1.0;

/// Adds Gaussians where `start` (at keyframe 0) leaves `frame` uncovered; returns how many. A
/// start without keyframes, a frame whose RGB does not match its camera, or a spacing of 0 adds
/// none.
pub fn cover_frame(start: &mut FittedScene, frame: &Frame, spacing_px: u32) -> usize {
    let camera = &frame.camera;
    let (w, h) = (camera.width() as usize, camera.height() as usize);
    let Some(first) = start.sets.first() else {
        return 0;
    };
    if spacing_px == 0 || frame.rgb.len() != 3 * w * h {
        return 0;
    }
    let options = RenderOptions {
        features: false,
        ..RenderOptions::default()
    };
    let plain = strip_features(first);
    let Ok(image) = CpuRasterizer::new().render(&plain, camera, &options) else {
        return 0;
    };
    let s = spacing_px as usize;
    let (gw, gh) = (w.div_ceil(s), h.div_ceil(s));
    // The pixel a cell is judged and placed at: its centre, inside the frame.
    let centre = |c: usize, size: usize| (c * s + s / 2).min(size - 1);
    let mut depth = vec![None; gw * gh];
    for gy in 0..gh {
        for gx in 0..gw {
            let p = centre(gy, h) * w + centre(gx, w);
            let d = image.expected_depth[p];
            if image.alpha[p] >= COVERED && d.is_finite() && d > 0.0 {
                depth[gy * gw + gx] = Some(d);
            }
        }
    }
    let uncovered: Vec<usize> = (0..gw * gh).filter(|&c| depth[c].is_none()).collect();
    if uncovered.is_empty() {
        return 0;
    }
    let fallback = median_depth(first, camera).unwrap_or(1.0);
    let nearest = nearest_depth(&depth, gw, gh, fallback);
    let k = camera.intrinsics();
    let focal = 0.5 * (k.fx + k.fy);
    let to_world = camera.camera_to_world();
    let mut added = Columns::default();
    for c in uncovered {
        let (gx, gy) = (c % gw, c / gw);
        let (px, py) = (centre(gx, w), centre(gy, h));
        let z = nearest[c];
        let (u, v) = (px as f32 + 0.5, py as f32 + 0.5);
        let local = Vec3::new((u - k.cx) / k.fx * z, (v - k.cy) / k.fy * z, z);
        let world = to_world.transform_point3(local);
        let sigma = SIZE * s as f32 * z / focal;
        if !(world.is_finite() && sigma.is_finite() && sigma > 0.0) {
            continue;
        }
        added.positions.push(world.to_array());
        added.scales.push([sigma; 3]);
        added.rotations.push([1.0, 0.0, 0.0, 0.0]);
        added.opacities.push(OPACITY);
        added
            .colors
            .push(cell_colour(&frame.rgb, w, h, gx * s, gy * s, s));
    }
    let count = added.positions.len();
    if count == 0 {
        return 0;
    }
    for set in &mut start.sets {
        *set = added.appended_to(set);
    }
    start.static_mask.resize(start.len(), true);
    count
}

/// The set without its feature block (rendering and the fit ignore it).
fn strip_features(set: &GaussianSet) -> GaussianSet {
    let mut plain = set.clone();
    plain.take_features();
    plain
}

/// The median camera-space depth of the Gaussians in front of the camera.
fn median_depth(set: &GaussianSet, camera: &c4g_scene::Camera) -> Option<f32> {
    let mut z: Vec<f32> = set
        .positions()
        .iter()
        .map(|&p| camera.to_camera(Vec3::from_array(p)).z)
        .filter(|z| z.is_finite() && *z > 0.0)
        .collect();
    if z.is_empty() {
        return None;
    }
    z.sort_by(f32::total_cmp);
    Some(z[z.len() / 2])
}

/// Every cell's depth: its own where covered, else the nearest covered cell's (8-neighbour
/// breadth-first from every covered cell at once), else `fallback`.
fn nearest_depth(depth: &[Option<f32>], gw: usize, gh: usize, fallback: f32) -> Vec<f32> {
    let mut out: Vec<Option<f32>> = depth.to_vec();
    let mut queue: VecDeque<usize> = (0..depth.len()).filter(|&c| depth[c].is_some()).collect();
    while let Some(c) = queue.pop_front() {
        let (x, y) = ((c % gw) as isize, (c / gw) as isize);
        for (dx, dy) in [
            (-1, 0),
            (1, 0),
            (0, -1),
            (0, 1),
            (-1, -1),
            (1, -1),
            (-1, 1),
            (1, 1),
        ] {
            let (nx, ny) = (x + dx, y + dy);
            if nx < 0 || ny < 0 || nx >= gw as isize || ny >= gh as isize {
                continue;
            }
            let n = ny as usize * gw + nx as usize;
            if out[n].is_none() {
                out[n] = out[c];
                queue.push_back(n);
            }
        }
    }
    out.into_iter().map(|d| d.unwrap_or(fallback)).collect()
}

/// The mean colour of the frame's pixels in the cell at (`x0`, `y0`), `s` pixels a side.
fn cell_colour(rgb: &[f32], w: usize, h: usize, x0: usize, y0: usize, s: usize) -> [f32; 3] {
    let mut sum = [0.0f32; 3];
    let mut n = 0.0f32;
    for y in y0..(y0 + s).min(h) {
        for x in x0..(x0 + s).min(w) {
            for (j, v) in sum.iter_mut().enumerate() {
                *v += rgb[3 * (y * w + x) + j];
            }
            n += 1.0;
        }
    }
    sum.map(|v| (v / n.max(1.0)).max(0.0))
}

#[derive(Default)]
struct Columns {
    positions: Vec<[f32; 3]>,
    scales: Vec<[f32; 3]>,
    rotations: Vec<[f32; 4]>,
    opacities: Vec<f32>,
    colors: Vec<[f32; 3]>,
}

impl Columns {
    fn appended_to(&self, set: &GaussianSet) -> GaussianSet {
        let join = |a: &[[f32; 3]], b: &[[f32; 3]]| [a, b].concat();
        GaussianSet::new(
            join(set.positions(), &self.positions),
            join(set.scales(), &self.scales),
            [set.rotations(), &self.rotations].concat(),
            [set.opacities(), &self.opacities].concat(),
            join(set.colors(), &self.colors),
        )
        .unwrap_or_else(|_| unreachable!("every column gains the same rows"))
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use c4g_scene::{Camera, Intrinsics};

    fn camera(w: u32, h: u32) -> Camera {
        Camera::from_world_to_camera_matrix(
            Intrinsics {
                fx: w as f32,
                fy: w as f32,
                cx: w as f32 / 2.0,
                cy: h as f32 / 2.0,
                width: w,
                height: h,
            },
            Default::default(),
        )
        .unwrap()
    }

    fn frame(w: u32, h: u32) -> Frame {
        let rgb = (0..w * h)
            .flat_map(|p| {
                let (x, y) = ((p % w) as f32 / w as f32, (p / w) as f32 / h as f32);
                [x, y, 0.5]
            })
            .collect();
        Frame {
            time: 0.0,
            rgb,
            camera: camera(w, h),
        }
    }

    /// A dense grid of Gaussians at depth `z` over the pixels `x0..x1` × `y0..y1` of a `w`-wide
    /// camera with `fx = w` (as [`camera`] makes).
    fn patch(w: u32, h: u32, x0: u32, x1: u32, y0: u32, y1: u32, z: f32) -> GaussianSet {
        let mut g = Vec::new();
        for y in (y0..y1).step_by(2) {
            for x in (x0..x1).step_by(2) {
                let (u, v) = (x as f32 + 1.0, y as f32 + 1.0);
                g.push(c4g_scene::Gaussian {
                    position: Vec3::new(
                        (u - w as f32 / 2.0) / w as f32 * z,
                        (v - h as f32 / 2.0) / w as f32 * z,
                        z,
                    ),
                    scale: Vec3::splat(1.5 * z / w as f32),
                    rotation: glam::Quat::IDENTITY,
                    opacity: 0.95,
                    color: Vec3::splat(0.3),
                });
            }
        }
        GaussianSet::from_gaussians(g)
    }

    fn scene(set: GaussianSet) -> FittedScene {
        FittedScene::new(vec![(0.0, set.clone()), (1.0, set)]).unwrap()
    }

    fn alpha(scene: &FittedScene, frame: &Frame) -> Vec<f32> {
        let options = RenderOptions {
            features: false,
            ..RenderOptions::default()
        };
        CpuRasterizer::new()
            .render(&scene.sets[0], &frame.camera, &options)
            .unwrap()
            .alpha
    }

    #[test]
    fn a_start_covering_the_centre_gains_gaussians_only_outside_it_at_its_depth() {
        let (w, h) = (64, 40);
        let f = frame(w, h);
        // The centre square, as the model sees it: columns 12..52.
        let mut s = scene(patch(w, h, 12, 52, 0, 40, 2.0));
        let before = s.len();
        let added = cover_frame(&mut s, &f, 4);
        assert!(added > 0);
        assert_eq!(s.len(), before + added);
        assert_eq!(s.static_mask.len(), s.len());
        assert!(s.static_mask[before..].iter().all(|&m| m));
        assert!(s.static_mask[..before].iter().all(|&m| !m));
        assert_eq!(s.sets[0], s.sets[1], "the same values at every keyframe");
        for (&p, &c) in s.sets[0].positions()[before..]
            .iter()
            .zip(&s.sets[0].colors()[before..])
        {
            let u = f.camera.project(Vec3::from_array(p)).unwrap();
            assert!(
                !(13.0..51.0).contains(&u.x),
                "added at {u} inside the covered centre"
            );
            assert!(
                (p[2] - 2.0).abs() < 0.05,
                "at the covered depth, not {}",
                p[2]
            );
            // The frame's red channel is x / w: the colour follows the pixel.
            assert!((c[0] - u.x / w as f32).abs() < 0.05);
        }
        s.sets[0].validate().unwrap();
    }

    #[test]
    fn a_fully_covered_frame_gains_nothing() {
        let (w, h) = (32, 24);
        let mut s = scene(patch(w, h, 0, 32, 0, 24, 1.5));
        let original = s.clone();
        assert_eq!(cover_frame(&mut s, &frame(w, h), 4), 0);
        assert_eq!(s, original);
    }

    #[test]
    fn an_empty_start_is_filled_at_depth_one_and_covers_the_frame() {
        let (w, h) = (48, 32);
        let f = frame(w, h);
        let mut s = scene(GaussianSet::default());
        assert_eq!(cover_frame(&mut s, &f, 4), 12 * 8);
        assert!(s.sets[0].positions().iter().all(|p| p[2] == 1.0));
        let a = alpha(&s, &f);
        let low = a.iter().filter(|&&v| v < 0.9).count();
        assert!(low * 50 < a.len(), "{low} of {} pixels under 0.9", a.len());
    }

    #[test]
    fn after_covering_alpha_is_at_least_0_9_almost_everywhere() {
        for (w, h, spacing) in [(64, 40, 4), (80, 48, 3), (50, 30, 5)] {
            let f = frame(w, h);
            let side = h;
            let x0 = (w - side) / 2;
            let mut s = scene(patch(w, h, x0, x0 + side, 0, h, 3.0));
            cover_frame(&mut s, &f, spacing);
            let a = alpha(&s, &f);
            let low = a.iter().filter(|&&v| v < 0.9).count();
            assert!(
                low * 50 < a.len(),
                "{w}x{h}/{spacing}: {low} pixels under 0.9"
            );
        }
    }

    #[test]
    fn nothing_in_front_falls_back_to_the_median_depth_then_one() {
        let (w, h) = (32, 24);
        let f = frame(w, h);
        // Gaussians behind the camera cover nothing: the fallback is depth 1.
        let behind = patch(w, h, 0, 32, 0, 24, -2.0);
        let mut s = scene(behind.clone());
        let added = cover_frame(&mut s, &f, 8);
        assert_eq!(added, 4 * 3);
        assert!(
            s.sets[0].positions()[behind.len()..]
                .iter()
                .all(|p| p[2] == 1.0)
        );
        // Tiny far Gaussians cover no grid cell: their median depth is used.
        let mut faint = patch(w, h, 0, 4, 0, 4, 5.0).iter().collect::<Vec<_>>();
        for g in &mut faint {
            g.scale = Vec3::splat(1e-4);
        }
        let faint = GaussianSet::from_gaussians(faint);
        let mut s = scene(faint.clone());
        cover_frame(&mut s, &f, 8);
        assert!(
            s.sets[0].positions()[faint.len()..]
                .iter()
                .all(|p| (p[2] - 5.0).abs() < 1e-5)
        );
    }

    #[test]
    fn a_zero_spacing_or_a_mismatched_frame_adds_nothing() {
        let f = frame(16, 16);
        let mut s = scene(GaussianSet::default());
        assert_eq!(cover_frame(&mut s, &f, 0), 0);
        let short = Frame {
            rgb: vec![0.0; 3],
            ..f
        };
        assert_eq!(cover_frame(&mut s, &short, 4), 0);
        assert!(s.is_empty());
    }
}
