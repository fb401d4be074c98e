//! The wgpu rasterizer against the float64 reference (fixture scenes, both footprints), against
//! the CPU rasterizer (random scenes) and at the extremes of its inputs and of the device's limits.
//!
//! Tolerances: on the fixture scenes, which keep clear of the forward model's steps, the CPU
//! rasterizer's: RGB, alpha and features within 2e-3 absolute, depth and expected depth within
//! 1e-3 relative where alpha > 0.5 (for the 3DGS footprint too: its scenes keep its tile ranges
//! 1e-3 pixels or more from moving, which covers f32 rounding of the radius and the tile ends).
//! Random scenes do not keep clear of the steps (the 3-sigma cut, the 1/255 cut, the transmittance
//! stop, a 3DGS tile end), where an f32 rounding may flip one pixel (a 3DGS tile end: a row of
//! them) by up to ~1e-2; there 99.9 % of the values must agree within 2e-3 and all within 5e-2.
//!
//! Without an adapter these tests print "skipped: ..." and pass, unless `CI` is set (CI installs
//! lavapipe, so there a missing adapter is a failure). `C4G_WGPU_ADAPTER` picks the adapter.
#![cfg(feature = "gpu")]
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use std::sync::OnceLock;

use c4g_renderer::raster::gpu::{AdapterChoice, GpuOptions};
use c4g_renderer::{CpuRasterizer, GpuRasterizer, Image, Rasterizer, RenderOptions};
use c4g_scene::Footprint;
use c4g_scene::{Camera, FeatureBlock, GaussianSet, Intrinsics, NormalizedIntrinsics, SceneError};
use common::*;
use glam::{Affine3A, Quat, Vec3};

/// The shared rasterizer, or `None` (after saying so) where no adapter exists outside CI.
fn gpu() -> Option<&'static GpuRasterizer> {
    static GPU: OnceLock<Option<GpuRasterizer>> = OnceLock::new();
    GPU.get_or_init(|| match GpuRasterizer::new() {
        Ok(gpu) => {
            println!("adapter: {}", gpu.adapter());
            Some(gpu)
        }
        Err(e) if std::env::var_os("CI").is_none() => {
            println!("skipped: {e}");
            None
        }
        Err(e) => panic!("CI is set but the GPU rasterizer cannot start: {e}"),
    })
    .as_ref()
}

/// A rasterizer whose buffers hold at most `bytes`, so frames split into bands and chunks.
fn small_gpu(bytes: u64) -> Option<GpuRasterizer> {
    gpu()?;
    Some(
        GpuRasterizer::with_options(GpuOptions {
            adapter: AdapterChoice::from_env(),
            max_buffer_bytes: Some(bytes),
        })
        .unwrap(),
    )
}

fn camera(width: u32, height: u32) -> Camera {
    Camera::from_normalized(
        NormalizedIntrinsics::C4G_DEFAULT,
        width,
        height,
        Affine3A::IDENTITY,
    )
    .unwrap()
}

/// A small deterministic generator (no dependency needed for test data).
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> f32 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (self.0 >> 40) as f32 / (1u64 << 24) as f32
    }

    fn range(&mut self, lo: f32, hi: f32) -> f32 {
        lo + (hi - lo) * self.next()
    }
}

/// `n` Gaussians in front of the default camera, with `channels` features when non-zero.
fn random_set(n: usize, seed: u64, scale: (f32, f32), channels: usize) -> GaussianSet {
    let mut rng = Rng(seed);
    let mut g = |_| {
        let z = rng.range(1.0, 6.0);
        let pos = [rng.range(-0.6, 0.6) * z, rng.range(-0.6, 0.6) * z, z];
        let s = [
            rng.range(scale.0, scale.1),
            rng.range(scale.0, scale.1),
            rng.range(scale.0, scale.1),
        ];
        let q = Quat::from_xyzw(
            rng.range(-1.0, 1.0),
            rng.range(-1.0, 1.0),
            rng.range(-1.0, 1.0),
            rng.range(-1.0, 1.0),
        )
        .normalize();
        let rot = [q.w, q.x, q.y, q.z];
        let o = rng.range(0.05, 1.0);
        let c = [rng.next(), rng.next(), rng.next()];
        (pos, s, rot, o, c)
    };
    let items: Vec<_> = (0..n).map(&mut g).collect();
    let set = GaussianSet::new(
        items.iter().map(|i| i.0).collect(),
        items.iter().map(|i| i.1).collect(),
        items.iter().map(|i| i.2).collect(),
        items.iter().map(|i| i.3).collect(),
        items.iter().map(|i| i.4).collect(),
    )
    .unwrap();
    if channels == 0 {
        return set;
    }
    let values = (0..n * channels).map(|_| rng.range(-1.0, 1.0)).collect();
    set.with_features(FeatureBlock::new(channels, values).unwrap())
        .unwrap()
}

fn one(pos: [f32; 3], scale: [f32; 3], opacity: f32, color: [f32; 3]) -> GaussianSet {
    GaussianSet::new(
        vec![pos],
        vec![scale],
        vec![[1.0, 0.0, 0.0, 0.0]],
        vec![opacity],
        vec![color],
    )
    .unwrap()
}

fn render(gpu: &GpuRasterizer, set: &GaussianSet, cam: &Camera) -> Image {
    gpu.render(set, cam, &RenderOptions::default()).unwrap()
}

fn cpu(set: &GaussianSet, cam: &Camera) -> Image {
    CpuRasterizer::new()
        .render(set, cam, &RenderOptions::default())
        .unwrap()
}

/// Share of values within `tolerance`, and the largest difference.
fn agreement(a: &[f32], b: &[f32], tolerance: f32) -> (f64, f32) {
    assert_eq!(a.len(), b.len());
    let mut close = 0usize;
    let mut worst = 0.0f32;
    for (x, y) in a.iter().zip(b) {
        let d = (x - y).abs();
        assert!(d.is_finite(), "{x} vs {y}");
        if d <= tolerance {
            close += 1;
        }
        worst = worst.max(d);
    }
    (close as f64 / a.len().max(1) as f64, worst)
}

/// Holds `got` to `expected` with the random-scene tolerances, and prints the agreement.
fn assert_close_to_cpu(what: &str, got: &Image, expected: &Image) {
    let d = compare(got, expected);
    println!("{what}: {d:?}");
    let mut planes = vec![
        ("rgb", &got.rgb, &expected.rgb),
        ("alpha", &got.alpha, &expected.alpha),
    ];
    if let (Some(g), Some(e)) = (&got.features, &expected.features) {
        planes.push(("features", &g.values, &e.values));
    }
    for (name, g, e) in planes {
        let (share, worst) = agreement(g, e, 2e-3);
        assert!(
            share >= 0.999 && worst <= 5e-2,
            "{what} {name}: {:.4} % within 2e-3, worst {worst}",
            share * 100.0
        );
    }
    let depth_scale = expected.depth.iter().fold(1.0f32, |m, v| m.max(v.abs()));
    let (share, _) = agreement(&got.depth, &expected.depth, 1e-3 * depth_scale);
    assert!(share >= 0.999, "{what} depth: {share}");
}

fn is_background(image: &Image, background: [f32; 3]) -> bool {
    image.alpha.iter().all(|&a| a == 0.0)
        && image.depth.iter().all(|&d| d == 0.0)
        && image
            .rgb
            .chunks_exact(3)
            .all(|p| p == background.as_slice())
}

// ---- the fixture scenes, against the float64 reference -------------------------------------

fn check_scene(name: &str) {
    let Some(gpu) = gpu() else { return };
    let scene = load_scene(name);
    let got = gpu
        .render(&scene.gaussians, &scene.camera, &scene.options)
        .unwrap();
    let d = compare(&got, &scene.expected);
    println!("{name} vs reference: {d:?}");
    d.assert_within_reference_tolerance(name);
    let on_cpu = CpuRasterizer::new()
        .render(&scene.gaussians, &scene.camera, &scene.options)
        .unwrap();
    let d = compare(&got, &on_cpu);
    println!("{name} vs CPU: {d:?}");
    assert!(
        d.rgb_max_abs <= 2e-3 && d.features_max_abs <= 2e-3,
        "{name}: {d:?}"
    );
}

#[test]
fn cloud_matches_the_reference() {
    check_scene("cloud");
}

#[test]
fn extremes_match_the_reference() {
    check_scene("extremes");
}

#[test]
fn fullscreen_matches_the_reference() {
    check_scene("fullscreen");
}

#[test]
fn stack_matches_the_reference() {
    check_scene("stack");
}

#[test]
fn background_matches_the_reference() {
    check_scene("background");
}

#[test]
fn large_matches_the_reference() {
    check_scene("large");
}

#[test]
fn every_scene_matches_the_reference_with_the_3dgs_footprint() {
    for name in SCENES_3DGS {
        check_scene(name);
    }
}

// ---- random scenes, against the CPU rasterizer ---------------------------------------------

#[test]
fn random_scenes_match_the_cpu_rasterizer() {
    let Some(gpu) = gpu() else { return };
    for (seed, n, size, scale, channels) in [
        (1, 2000, (128, 96), (0.005, 0.08), 0),
        (2, 500, (200, 120), (0.02, 0.3), 5),
        (3, 3000, (96, 96), (0.001, 0.02), 9),
        (4, 50, (64, 64), (0.2, 1.0), 1),
    ] {
        let set = random_set(n, seed, scale, channels);
        let cam = camera(size.0, size.1);
        assert_close_to_cpu(
            &format!("seed {seed}"),
            &render(gpu, &set, &cam),
            &cpu(&set, &cam),
        );
    }
}

#[test]
fn random_scenes_match_the_cpu_rasterizer_with_the_3dgs_footprint() {
    let Some(gpu) = gpu() else { return };
    let options = RenderOptions {
        footprint: Footprint::Tiles3dgs,
        ..RenderOptions::default()
    };
    for (seed, n, size, scale, channels) in [
        (1, 2000, (128, 96), (0.005, 0.08), 0),
        (2, 500, (200, 120), (0.02, 0.3), 5),
        (3, 3000, (96, 96), (0.001, 0.02), 9),
        (4, 50, (64, 64), (0.2, 1.0), 1),
    ] {
        let set = random_set(n, seed, scale, channels);
        let cam = camera(size.0, size.1);
        assert_close_to_cpu(
            &format!("3dgs seed {seed}"),
            &gpu.render(&set, &cam, &options).unwrap(),
            &CpuRasterizer::new().render(&set, &cam, &options).unwrap(),
        );
    }
}

#[test]
fn the_same_scene_renders_the_same_image_every_time() {
    let Some(gpu) = gpu() else { return };
    let set = random_set(3000, 7, (0.01, 0.1), 3);
    let cam = camera(160, 120);
    let first = render(gpu, &set, &cam);
    assert_eq!(render(gpu, &set, &cam), first);
    // Buffers sized by a larger frame in between are reused without changing anything.
    render(
        gpu,
        &random_set(20_000, 8, (0.01, 0.1), 7),
        &camera(300, 200),
    );
    assert_eq!(render(gpu, &set, &cam), first);
}

#[test]
fn bands_and_chunks_change_nothing() {
    let Some(gpu) = gpu() else { return };
    let set = random_set(4000, 11, (0.3, 1.5), 3);
    let cam = camera(320, 240);
    let whole = render(gpu, &set, &cam);
    // 256 KiB buffers: bands of one tile row, each with more pairs than one chunk holds.
    let small = small_gpu(256 << 10).unwrap();
    assert_eq!(render(&small, &set, &cam), whole);
}

#[test]
fn bands_and_chunks_change_nothing_with_the_3dgs_footprint() {
    let Some(gpu) = gpu() else { return };
    let options = RenderOptions {
        footprint: Footprint::Tiles3dgs,
        ..RenderOptions::default()
    };
    let set = random_set(2000, 12, (0.3, 1.5), 3);
    let cam = camera(320, 240);
    let whole = gpu.render(&set, &cam, &options).unwrap();
    let small = small_gpu(256 << 10).unwrap();
    assert_eq!(small.render(&set, &cam, &options).unwrap(), whole);
}

#[test]
fn depth_ties_are_drawn_in_index_order() {
    let Some(gpu) = gpu() else { return };
    let cam = camera(32, 32);
    let mut red = one([0.0, 0.0, 2.0], [0.2; 3], 0.7, [1.0, 0.0, 0.0]);
    let blue = one([0.0, 0.0, 2.0], [0.2; 3], 0.7, [0.0, 0.0, 1.0]);
    red = GaussianSet::from_gaussians(red.iter().chain(blue.iter()));
    let image = render(gpu, &red, &cam);
    let centre = (16 * 32 + 16) * 3;
    assert!(
        image.rgb[centre] > image.rgb[centre + 2],
        "the first of a tie is in front"
    );
    assert_close_to_cpu("tie", &image, &cpu(&red, &cam));
}

// ---- extremes of the inputs -----------------------------------------------------------------

#[test]
fn an_empty_set_renders_the_background() {
    let Some(gpu) = gpu() else { return };
    let options = RenderOptions {
        background: [0.1, 0.2, 0.3],
        ..RenderOptions::default()
    };
    let image = gpu
        .render(&GaussianSet::default(), &camera(20, 10), &options)
        .unwrap();
    assert!(is_background(&image, options.background));
    assert!(image.features.is_none());
}

#[test]
fn gaussians_behind_the_camera_or_the_near_plane_draw_nothing() {
    let Some(gpu) = gpu() else { return };
    let cam = camera(48, 48);
    let options = RenderOptions::default();
    for z in [-2.0, 0.0, 0.005, 150.0] {
        let image = gpu
            .render(&one([0.0, 0.0, z], [0.5; 3], 1.0, [1.0; 3]), &cam, &options)
            .unwrap();
        assert!(is_background(&image, [0.0; 3]), "z = {z}");
    }
    // Centre just in front of the near plane, body straddling it: drawn, huge on screen.
    let straddling = one([0.0, 0.0, 0.02], [0.05; 3], 0.8, [1.0; 3]);
    let image = render(gpu, &straddling, &cam);
    assert!(image.alpha.iter().all(|&a| a > 0.5));
    assert_close_to_cpu("straddling", &image, &cpu(&straddling, &cam));
}

#[test]
fn zero_and_huge_scales_render_like_the_cpu() {
    let Some(gpu) = gpu() else { return };
    let cam = camera(64, 64);
    let dot = one([0.0, 0.0, 2.0], [0.0; 3], 1.0, [1.0, 0.5, 0.25]);
    let image = render(gpu, &dot, &cam);
    let lit = image.alpha.iter().filter(|&&a| a > 0.0).count();
    assert!(
        (1..=25).contains(&lit),
        "a zero-scale Gaussian covers about a pixel: {lit}"
    );
    assert_close_to_cpu("zero scale", &image, &cpu(&dot, &cam));

    let huge = one([0.3, -0.2, 5.0], [1e6; 3], 0.6, [0.2, 0.4, 0.8]);
    let image = render(gpu, &huge, &cam);
    assert!(
        image.alpha.iter().all(|&a| (a - 0.6).abs() < 1e-4),
        "uniform opacity"
    );
    assert_close_to_cpu("1e6 scale", &image, &cpu(&huge, &cam));
}

#[test]
fn opacity_zero_draws_nothing_and_opacity_one_is_capped() {
    let Some(gpu) = gpu() else { return };
    let cam = camera(32, 32);
    let none = render(gpu, &one([0.0, 0.0, 2.0], [0.3; 3], 0.0, [1.0; 3]), &cam);
    assert!(is_background(&none, [0.0; 3]));
    // Wide enough that the pixels next to its centre would exceed the cap.
    let full = render(gpu, &one([0.0, 0.0, 2.0], [3.0; 3], 1.0, [1.0; 3]), &cam);
    let peak = full.alpha.iter().fold(0.0f32, |m, &a| m.max(a));
    assert!((peak - 0.99).abs() < 1e-6, "{peak}");
}

#[test]
fn non_finite_gaussians_are_skipped_without_touching_other_pixels() {
    let Some(gpu) = gpu() else { return };
    let cam = camera(96, 64);
    let clean = random_set(300, 21, (0.02, 0.2), 2);
    let mut gaussians: Vec<_> = clean.iter().collect();
    let mut features = clean.features().unwrap().values().to_vec();
    for (k, bad) in [f32::NAN, f32::INFINITY, f32::NEG_INFINITY]
        .into_iter()
        .enumerate()
    {
        for field in 0..6 {
            let mut g = gaussians[(k * 6 + field) * 7];
            match field {
                0 => g.position.y = bad,
                1 => g.scale.z = bad,
                2 => g.rotation = Quat::from_xyzw(bad, 0.0, 0.0, 1.0),
                3 => g.opacity = bad,
                4 => g.color.x = bad,
                _ => g.position = Vec3::new(bad, bad, bad),
            }
            gaussians.push(g);
            features.extend([0.5, -0.5]);
        }
    }
    // And one whose only fault is its feature vector.
    gaussians.push(gaussians[3]);
    features.extend([f32::NAN, 0.0]);
    let dirty = GaussianSet::from_gaussians(gaussians)
        .with_features(FeatureBlock::new(2, features).unwrap())
        .unwrap();
    assert_eq!(render(gpu, &dirty, &cam), render(gpu, &clean, &cam));
}

#[test]
fn one_gaussian_can_cover_the_whole_screen() {
    let Some(gpu) = gpu() else { return };
    let cam = camera(300, 200);
    let wall = one([0.0, 0.0, 3.0], [20.0, 20.0, 0.1], 0.9, [0.3, 0.6, 0.9]);
    let image = render(gpu, &wall, &cam);
    assert!(image.alpha.iter().all(|&a| a > 0.85));
    assert_close_to_cpu("wall", &image, &cpu(&wall, &cam));
}

#[test]
fn a_one_pixel_image_renders() {
    let Some(gpu) = gpu() else { return };
    let cam = camera(1, 1);
    let set = random_set(100, 31, (0.05, 0.5), 3);
    let image = render(gpu, &set, &cam);
    assert_eq!((image.rgb.len(), image.alpha.len()), (3, 1));
    assert_close_to_cpu("1x1", &image, &cpu(&set, &cam));
}

#[test]
fn a_4096_square_image_renders_in_bands() {
    let Some(gpu) = gpu() else { return };
    let cam = camera(4096, 4096);
    let set = random_set(2000, 41, (0.002, 0.02), 0);
    // On a device that binds 128 MiB (lavapipe) this is three bands of tile rows.
    let image = render(gpu, &set, &cam);
    assert_close_to_cpu("4096²", &image, &cpu(&set, &cam));
}

#[test]
fn tiny_and_huge_focal_lengths_render_like_the_cpu() {
    let Some(gpu) = gpu() else { return };
    let set = random_set(500, 51, (0.01, 0.2), 0);
    for focal in [1e-3, 0.5, 1e5] {
        let k = Intrinsics {
            fx: focal,
            fy: focal,
            cx: 32.0,
            cy: 24.0,
            width: 64,
            height: 48,
        };
        let cam = Camera::new(k, Affine3A::IDENTITY).unwrap();
        let image = render(gpu, &set, &cam);
        assert!(image.rgb.iter().all(|v| v.is_finite()));
        assert_close_to_cpu(&format!("focal {focal}"), &image, &cpu(&set, &cam));
    }
}

#[test]
fn a_million_gaussians_render_like_the_cpu() {
    let Some(gpu) = gpu() else { return };
    let set = random_set(1_000_000, 61, (0.001, 0.01), 0);
    let cam = camera(256, 256);
    assert_close_to_cpu("1M", &render(gpu, &set, &cam), &cpu(&set, &cam));
}

#[test]
fn feature_widths_of_any_size_render_like_the_cpu() {
    let Some(gpu) = gpu() else { return };
    let cam = camera(80, 60);
    for channels in [1, 3, 4, 8, 13] {
        let set = random_set(400, 70 + channels as u64, (0.02, 0.2), channels);
        let image = render(gpu, &set, &cam);
        assert_eq!(image.features.as_ref().unwrap().channels, channels);
        assert_close_to_cpu(&format!("{channels} channels"), &image, &cpu(&set, &cam));
        let without = gpu
            .render(
                &set,
                &cam,
                &RenderOptions {
                    features: false,
                    ..RenderOptions::default()
                },
            )
            .unwrap();
        assert!(without.features.is_none());
        assert_eq!(without.rgb, image.rgb);
    }
}

#[test]
fn an_adapter_that_does_not_exist_is_a_clear_error() {
    let err = GpuRasterizer::with_options(GpuOptions {
        adapter: AdapterChoice::Named("no adapter is called this".to_owned()),
        max_buffer_bytes: None,
    })
    .unwrap_err();
    assert!(matches!(err, SceneError::GpuUnavailable(_)), "{err}");
    println!("{err}");
}
