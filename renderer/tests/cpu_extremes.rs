//! The CPU rasterizer at the edges of its input space: each extreme is its own test.
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use c4g_renderer::raster::{ALPHA_MAX, NEAR};
use c4g_renderer::{CpuRasterizer, Image, Rasterizer, RenderOptions};
use c4g_scene::{Camera, FeatureBlock, GaussianSet, Intrinsics};
use common::*;

const GREY: [f32; 3] = [0.5, 0.5, 0.5];

fn render(set: &GaussianSet, camera: &Camera) -> Image {
    CpuRasterizer::new()
        .render(set, camera, &RenderOptions::default())
        .unwrap()
}

fn drawn(image: &Image) -> usize {
    image.alpha.iter().filter(|a| **a > 0.0).count()
}

fn centre(image: &Image) -> usize {
    (image.height / 2 * image.width + image.width / 2) as usize
}

/// A scene of ordinary Gaussians, to check that an odd one leaves them untouched.
fn ordinary() -> GaussianSet {
    random_set(40, 7, 0.8, 0.05)
}

/// `ordinary()` with one more Gaussian appended.
fn with_extra(extra: ([f32; 3], [f32; 3], [f32; 4], f32, [f32; 3])) -> GaussianSet {
    let base = ordinary();
    let mut cols = (
        base.positions().to_vec(),
        base.scales().to_vec(),
        base.rotations().to_vec(),
        base.opacities().to_vec(),
        base.colors().to_vec(),
    );
    cols.0.push(extra.0);
    cols.1.push(extra.1);
    cols.2.push(extra.2);
    cols.3.push(extra.3);
    cols.4.push(extra.4);
    GaussianSet::new(cols.0, cols.1, cols.2, cols.3, cols.4).unwrap()
}

const ID: [f32; 4] = [1.0, 0.0, 0.0, 0.0];

#[test]
fn gaussians_behind_the_camera_are_skipped() {
    let cam = camera(64, 48, 50.0);
    let alone = render(&set_of(&[([0.0, 0.0, -1.0], [5.0; 3], 1.0, GREY)]), &cam);
    assert_eq!(drawn(&alone), 0);
    assert_eq!(
        render(
            &with_extra(([0.0, 0.0, -1.0], [5.0; 3], ID, 1.0, GREY)),
            &cam
        ),
        render(&ordinary(), &cam)
    );
}

#[test]
fn a_gaussian_exactly_on_the_near_plane_is_drawn_and_one_just_before_it_is_not() {
    let cam = camera(65, 49, 50.0);
    let on = render(&set_of(&[([0.0, 0.0, NEAR], [1e-4; 3], 1.0, GREY)]), &cam);
    assert_finite(&on);
    assert!((on.alpha[centre(&on)] - ALPHA_MAX).abs() < 1e-6);
    let before = render(
        &set_of(&[([0.0, 0.0, NEAR * 0.999], [1e-4; 3], 1.0, GREY)]),
        &cam,
    );
    assert_eq!(drawn(&before), 0);
}

#[test]
fn a_gaussian_straddling_the_near_plane_is_drawn_by_its_centre_only() {
    let cam = camera(64, 48, 50.0);
    // Centre in front, body reaching behind the camera: drawn, huge, finite.
    let front = render(&set_of(&[([0.01, 0.0, 0.02], [1.0; 3], 0.8, GREY)]), &cam);
    assert_finite(&front);
    assert_eq!(drawn(&front), 64 * 48);
    // Centre behind the near plane, body reaching into view: skipped.
    let behind = render(&set_of(&[([0.0, 0.0, 0.005], [1.0; 3], 0.8, GREY)]), &cam);
    assert_eq!(drawn(&behind), 0);
}

#[test]
fn zero_scale_is_a_pixel_sized_blob() {
    let cam = camera(65, 49, 50.0);
    let image = render(&set_of(&[([0.0, 0.0, 2.0], [0.0; 3], 1.0, GREY)]), &cam);
    assert_finite(&image);
    // Σ2D = 0.3 I: d² = r² / 0.3 ≤ 9 reaches the 3x3 block around the centre pixel.
    assert_eq!(drawn(&image), 9);
    let right = centre(&image) + 1;
    assert!((image.alpha[right] - (-0.5f32 / 0.3).exp()).abs() < 1e-6);
}

#[test]
fn a_scale_of_a_million_covers_the_image_at_its_opacity() {
    let cam = camera(64, 48, 50.0);
    let image = render(&set_of(&[([0.0, 0.0, 2.0], [1e6; 3], 0.6, GREY)]), &cam);
    assert_finite(&image);
    assert!(image.alpha.iter().all(|a| (a - 0.6).abs() < 1e-5));
    assert!(image.expected_depth.iter().all(|d| (d - 2.0).abs() < 1e-5));
}

#[test]
fn a_needle_of_scale_a_million_by_zero_stays_finite() {
    // Σ3D has rank one: the 2D covariance is (nearly) singular before the low-pass filter.
    let cam = camera(64, 48, 50.0);
    let set = set_of(&[([0.0, 0.0, 2.0], [1e6, 0.0, 0.0], 0.9, GREY)]);
    let image = render(&set, &cam);
    assert_finite(&image);
    // A horizontal line through the centre: the middle row is drawn, rows far from it are not.
    let w = image.width as usize;
    let mid = image.height as usize / 2;
    assert!(image.alpha[mid * w..(mid + 1) * w].iter().all(|a| *a > 0.5));
    assert!(image.alpha[..(mid - 3) * w].iter().all(|a| *a == 0.0));
}

#[test]
fn opacity_zero_changes_nothing() {
    let cam = camera(64, 48, 50.0);
    assert_eq!(
        render(
            &with_extra(([0.0, 0.0, 1.5], [0.3; 3], ID, 0.0, GREY)),
            &cam
        ),
        render(&ordinary(), &cam)
    );
}

#[test]
fn opacity_one_saturates_at_alpha_max() {
    let cam = camera(65, 49, 50.0);
    let image = render(
        &set_of(&[([0.0, 0.0, 2.0], [0.2; 3], 1.0, [1.0, 0.0, 0.0])]),
        &cam,
    );
    let c = centre(&image);
    assert!((image.alpha[c] - ALPHA_MAX).abs() < 1e-7);
    assert!((image.rgb[3 * c] - ALPHA_MAX).abs() < 1e-7);
}

#[test]
fn non_finite_parameters_are_skipped_without_touching_any_pixel() {
    let cam = camera(64, 48, 50.0);
    let clean = render(&ordinary(), &cam);
    for bad in [f32::NAN, f32::INFINITY, f32::NEG_INFINITY] {
        let g = ([0.0, 0.0, 2.0], [0.3; 3], ID, 0.9, GREY);
        let cases = [
            ([bad, 0.0, 2.0], g.1, g.2, g.3, g.4),
            (g.0, [0.3, bad, 0.3], g.2, g.3, g.4),
            (g.0, g.1, [1.0, 0.0, 0.0, bad], g.3, g.4),
            (g.0, g.1, g.2, bad, g.4),
            (g.0, g.1, g.2, g.3, [0.5, 0.5, bad]),
        ];
        for (k, case) in cases.into_iter().enumerate() {
            let image = render(&with_extra(case), &cam);
            assert_eq!(image, clean, "parameter {k} = {bad}");
        }
    }
}

#[test]
fn a_non_finite_feature_vector_skips_its_gaussian() {
    let cam = camera(64, 48, 50.0);
    let n = ordinary().len();
    let features = |rows: usize, bad: Option<f32>| {
        let mut values: Vec<f32> = (0..rows * 2).map(|i| i as f32 * 0.01).collect();
        if let Some(bad) = bad {
            values[rows * 2 - 1] = bad;
        }
        FeatureBlock::new(2, values).unwrap()
    };
    // The extra Gaussian sits in front of everything, in the middle: skipping it shows.
    let big = ([0.0, 0.0, 1.0], [0.2; 3], ID, 0.9, GREY);
    let drawn_with_good = render(
        &with_extra(big)
            .with_features(features(n + 1, None))
            .unwrap(),
        &cam,
    );
    let without = render(&ordinary().with_features(features(n, None)).unwrap(), &cam);
    assert_ne!(drawn_with_good, without);
    for bad in [f32::NAN, f32::INFINITY, f32::NEG_INFINITY] {
        let set = with_extra(big)
            .with_features(features(n + 1, Some(bad)))
            .unwrap();
        let image = render(&set, &cam);
        assert_eq!(image, without, "{bad}");
        // The skip does not depend on whether features are rendered.
        let options = RenderOptions {
            features: false,
            ..RenderOptions::default()
        };
        let plain = CpuRasterizer::new().render(&set, &cam, &options).unwrap();
        assert!(plain.features.is_none());
        assert_eq!(plain.rgb, without.rgb);
    }
}

#[test]
fn one_gaussian_covering_the_whole_screen_reaches_every_pixel() {
    let cam = camera(200, 150, 120.0);
    let image = render(
        &set_of(&[([0.0, 0.0, 1.0], [3.0, 2.0, 1.0], 0.7, GREY)]),
        &cam,
    );
    assert_finite(&image);
    assert_eq!(drawn(&image), 200 * 150);
}

#[test]
fn a_one_pixel_image_renders_the_gaussian_over_it() {
    let cam = camera(1, 1, 1.0);
    let image = render(
        &set_of(&[([0.0, 0.0, 2.0], [0.5; 3], 0.5, [1.0, 0.0, 0.0])]),
        &cam,
    );
    assert_eq!(image.rgb.len(), 3);
    // The pixel centre is the principal point: alpha = opacity there.
    assert!((image.alpha[0] - 0.5).abs() < 1e-6);
    assert!((image.rgb[0] - 0.5).abs() < 1e-6 && image.rgb[1] == 0.0);
}

#[test]
fn a_4096_square_image_matches_a_small_window_rendered_alone() {
    // The central 64x64 window of the big image, at (2016, 2016), is a 64x64 camera whose
    // principal point is shifted by the window's corner. Every Gaussian is inside both cameras'
    // FOV clamps (|x/z| ≤ 0.012 < 1.3 · 32 / 3000), so the two renders are one forward model.
    let focal = 3000.0;
    let big = camera(4096, 4096, focal);
    let k = big.intrinsics();
    let small = Camera::new(
        Intrinsics {
            cx: k.cx - 2016.0,
            cy: k.cy - 2016.0,
            width: 64,
            height: 64,
            ..*k
        },
        big.world_to_camera(),
    )
    .unwrap();
    let set = random_set(300, 3, 0.024, 0.002);
    let a = render(&set, &big);
    let b = render(&set, &small);
    assert_finite(&a);
    assert!(drawn(&b) > 1000);
    let mut worst = 0.0f32;
    for y in 0..64usize {
        for x in 0..64usize {
            let pa = (2016 + y) * 4096 + 2016 + x;
            let pb = y * 64 + x;
            worst = worst.max((a.alpha[pa] - b.alpha[pb]).abs());
            for c in 0..3 {
                worst = worst.max((a.rgb[3 * pa + c] - b.rgb[3 * pb + c]).abs());
            }
        }
    }
    // Pixel offsets are exact wherever a splat sits, so only last-bit roundings differ.
    assert!(worst < 1e-5, "{worst}");
}

#[test]
fn a_focal_length_of_a_thousandth_of_a_pixel_shrinks_everything_to_the_low_pass_blob() {
    let cam = camera(65, 49, 1e-3);
    let set = set_of(&[([1.0, -0.5, 2.0], [0.5; 3], 1.0, GREY)]);
    let image = render(&set, &cam);
    assert_finite(&image);
    // Projected at (32.5 + 5e-4, 24.5 - 2.5e-4) with Σ2D ≈ 0.3 I: the centre's 3x3 block.
    assert_eq!(drawn(&image), 9);
    assert!(image.alpha[centre(&image)] > 0.98);
}

#[test]
fn a_focal_length_of_ten_million_pixels_magnifies_without_overflow() {
    let cam = camera(64, 48, 1e7);
    let set = set_of(&[
        ([0.0, 0.0, 2.0], [0.01; 3], 0.7, GREY),
        // 2.5 million pixels to the right: off screen, whatever its size.
        ([0.5, 0.0, 2.0], [0.01; 3], 0.9, [1.0, 0.0, 0.0]),
    ]);
    let image = render(&set, &cam);
    assert_finite(&image);
    // σ = 1e7 · 0.01 / 2 = 5e4 pixels: flat over the image.
    assert!(
        image.alpha.iter().all(|a| (a - 0.7).abs() < 1e-4),
        "{:?}",
        &image.alpha[..4]
    );
}

#[test]
fn a_million_gaussians_render_finite_with_plausible_coverage() {
    let cam = camera(256, 256, 220.0);
    let set = random_set(1_000_000, 11, 1.0, 0.004);
    let image = render(&set, &cam);
    assert_finite(&image);
    // Centres spread over |u - 128| < 110 (x/z within ±0.5 at f = 220), about 20 per pixel there:
    // the central 200x200 is covered, the 18-pixel rim beyond the spread is not.
    let opaque = |x: usize, y: usize| image.alpha[y * 256 + x] > 0.5;
    let centre = (28..228)
        .flat_map(|y| (28..228).map(move |x| (x, y)))
        .filter(|&(x, y)| opaque(x, y))
        .count();
    assert!(centre > 200 * 200 * 99 / 100, "{centre}");
    let rim = (0..256).filter(|&y| opaque(2, y) || opaque(253, y)).count();
    assert_eq!(rim, 0);
    assert!(image.alpha.iter().all(|a| (0.0..=1.0).contains(a)));
    assert!(image.rgb.iter().all(|v| (0.0..=1.0).contains(v)));
    assert!(
        image
            .expected_depth
            .iter()
            .zip(&image.alpha)
            .all(|(d, a)| *a < 0.5 || (2.0..=6.0).contains(d))
    );
}

#[test]
fn invalid_render_options_are_rejected() {
    let cam = camera(8, 8, 8.0);
    let set = ordinary();
    for options in [
        RenderOptions {
            near: 0.0,
            ..RenderOptions::default()
        },
        RenderOptions {
            near: 5.0,
            far: 1.0,
            ..RenderOptions::default()
        },
        RenderOptions {
            background: [f32::NAN, 0.0, 0.0],
            ..RenderOptions::default()
        },
    ] {
        assert!(CpuRasterizer::new().render(&set, &cam, &options).is_err());
    }
}

#[test]
fn banding_the_tile_pairs_does_not_change_the_image() {
    // The pair budget bounds memory by binning a band of tiles at a time; with a budget of one
    // pair every tile is its own band.
    let cam = camera(200, 130, 150.0);
    let set = random_set(3000, 5, 1.0, 0.08);
    let one_band = render(&set, &cam);
    let per_tile = CpuRasterizer::new()
        .with_pair_budget(1)
        .render(&set, &cam, &RenderOptions::default())
        .unwrap();
    assert_eq!(one_band, per_tile);
}
