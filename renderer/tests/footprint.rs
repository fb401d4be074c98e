//! The two footprints, on both rasterizers (wgpu with the `gpu` feature and an adapter): where
//! they must differ (a large Gaussian's fringe beyond 3 sigma inside its 3DGS tiles; the pixel
//! column 3DGS's tile range leaves out of its own square) against closed forms, and where they
//! must agree (tiny Gaussians).
//!
//! Tolerances: the closed-form pixels keep clear of every step (|d² − 9| ≥ 0.15, alpha ≥ 1.14 ×
//! 1/255, the radius 0.66 from an integer, the tile ends 0.9 pixels or more from a multiple of 16),
//! so f32 arithmetic is the only difference: 1e-5 absolute on alpha values of ~1e-2. Tiny
//! Gaussians evaluate the same pixels in both footprints (argued in the test), so the images
//! differ only by f32 rounding of pixel offsets: 1e-5.
//!
//! Without an adapter the wgpu half prints "skipped: ..." and passes, unless `CI` is set.
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use c4g_renderer::{CpuRasterizer, Image, Rasterizer, RenderOptions};
use c4g_scene::Footprint;
use c4g_scene::{Camera, GaussianSet, Intrinsics};
use common::*;
use glam::Affine3A;

/// The CPU rasterizer, and the wgpu one when it is built and has an adapter.
fn rasterizers() -> Vec<(&'static str, &'static (dyn Rasterizer + Sync))> {
    static CPU: std::sync::OnceLock<CpuRasterizer> = std::sync::OnceLock::new();
    let mut all: Vec<(&'static str, &'static (dyn Rasterizer + Sync))> =
        vec![("cpu", CPU.get_or_init(CpuRasterizer::new))];
    #[cfg(feature = "gpu")]
    {
        use c4g_renderer::GpuRasterizer;
        static GPU: std::sync::OnceLock<Option<GpuRasterizer>> = std::sync::OnceLock::new();
        let gpu = GPU.get_or_init(|| match GpuRasterizer::new() {
            Ok(gpu) => Some(gpu),
            Err(e) if std::env::var_os("CI").is_none() => {
                println!("wgpu skipped: {e}");
                None
            }
            Err(e) => panic!("CI is set but the GPU rasterizer cannot start: {e}"),
        });
        if let Some(gpu) = gpu {
            all.push(("wgpu", gpu));
        }
    }
    all
}

fn options(footprint: Footprint) -> RenderOptions {
    RenderOptions {
        footprint,
        ..RenderOptions::default()
    }
}

fn render(r: &dyn Rasterizer, set: &GaussianSet, cam: &Camera, footprint: Footprint) -> Image {
    r.render(set, cam, &options(footprint)).unwrap()
}

#[test]
fn the_default_footprint_is_the_ellipse_and_the_names_are_ellipse_and_3dgs() {
    assert_eq!(RenderOptions::default().footprint, Footprint::Ellipse);
    assert_eq!(Footprint::default(), Footprint::Ellipse);
    for (footprint, name) in [
        (Footprint::Ellipse, "ellipse"),
        (Footprint::Tiles3dgs, "3dgs"),
    ] {
        assert_eq!(footprint.as_str(), name);
        assert_eq!(footprint.to_string(), name);
        let json = serde_json::to_string(&footprint).unwrap();
        assert_eq!(json, format!("\"{name}\""));
        assert_eq!(serde_json::from_str::<Footprint>(&json).unwrap(), footprint);
    }
    assert!(serde_json::from_str::<Footprint>("\"tiles\"").is_err());
}

#[test]
fn a_large_gaussian_s_fringe_beyond_3_sigma_inside_its_tiles_is_drawn_by_3dgs_not_by_the_ellipse() {
    // An isotropic Gaussian on the optical axis: Σ2D = ((f s / z)² + 0.3) I, σ ≈ 6.42 pixels.
    // 3DGS: λ = var + √0.1 (the discriminant floor), 3√λ = 19.34, r = 20; its centre is at
    // p = cx − 0.5 = 76.9, so its x tiles are [⌊56.9/16⌋, ⌊111.9/16⌋) = [3, 6): pixels 48..=95.
    let (f, cx, cy, z, s, opacity) = (64.0f32, 77.4f32, 64.0f32, 4.0f32, 0.4f32, 0.9f32);
    let cam = Camera::new(
        Intrinsics {
            fx: f,
            fy: f,
            cx,
            cy,
            width: 128,
            height: 128,
        },
        Affine3A::IDENTITY,
    )
    .unwrap();
    let set = set_of(&[([0.0, 0.0, z], [s; 3], opacity, [1.0; 3])]);
    let var = (f64::from(f) * f64::from(s) / f64::from(z)).powi(2)
        + f64::from(c4g_renderer::raster::EPS2D);
    let row = 64usize;
    let d2 = |x: usize| {
        let (dx, dy) = (
            x as f64 + 0.5 - f64::from(cx),
            row as f64 + 0.5 - f64::from(cy),
        );
        (dx * dx + dy * dy) / var
    };
    let closed = |x: usize| f64::from(opacity) * (-0.5 * d2(x)).exp();
    // What each footprint draws on that row: the fringe at 57 and 56 (d² 9.6 and 10.6, alpha
    // 0.0074 and 0.0045) only with the 3DGS tiles; pixel 96 (d² 8.85, inside 3 sigma) only with
    // the ellipse, as 3DGS's range ends at the tile before it although p + r = 96.9 lies past it;
    // 70 and 95 with both; 55 (alpha below 1/255) with neither.
    let cases = [
        (55, false, false),
        (56, false, true),
        (57, false, true),
        (70, true, true),
        (95, true, true),
        (96, true, false),
    ];
    assert!(d2(57) > 9.5 && d2(96) < 8.9 && closed(56) > 1.14 / 255.0 && closed(55) < 1.0 / 255.0);
    for (name, r) in rasterizers() {
        let ellipse = render(r, &set, &cam, Footprint::Ellipse);
        let tiles = render(r, &set, &cam, Footprint::Tiles3dgs);
        for (x, in_ellipse, in_tiles) in cases {
            for (image, drawn, footprint) in [
                (&ellipse, in_ellipse, "ellipse"),
                (&tiles, in_tiles, "3dgs"),
            ] {
                let got = f64::from(image.alpha[row * 128 + x]);
                let want = if drawn { closed(x) } else { 0.0 };
                assert!(
                    (got - want).abs() <= 1e-5,
                    "{name} {footprint}: pixel ({x}, {row}) alpha {got}, expected {want}"
                );
            }
        }
        // Over the whole image: the fringe is drawn by 3DGS only, the left-out column by the
        // ellipse only, and nothing lies outside the tiles (x, y in 48..96).
        let only = |a: &Image, b: &Image| {
            a.alpha
                .iter()
                .zip(&b.alpha)
                .filter(|&(&p, &q)| p > 0.0 && q == 0.0)
                .count()
        };
        assert!(only(&tiles, &ellipse) > 100, "{name}: the fringe");
        assert!(only(&ellipse, &tiles) > 0, "{name}: the left-out column");
        for (i, &a) in tiles.alpha.iter().enumerate() {
            let (x, y) = (i % 128, i / 128);
            if !((48..96).contains(&x) && (32..96).contains(&y)) {
                assert_eq!(a, 0.0, "{name}: ({x}, {y}) lies outside the 3DGS tiles");
            }
        }
    }
}

/// `n` Gaussians of world size under 2 mm at depth 2..6 in front of `common::camera`'s focal
/// length 100 (on screen well under 0.1 pixels: Σ2D is the 0.3 dilation within 0.013), with
/// opacities up to `max_opacity`.
fn tiny_set(n: usize, seed: u64, max_opacity: f32) -> GaussianSet {
    let mut rng = SplitMix(seed);
    let mut g = (vec![], vec![], vec![], vec![], vec![]);
    for _ in 0..n {
        let z = 2.0 + 4.0 * rng.unit();
        g.0.push([(rng.unit() - 0.5) * z, 0.75 * (rng.unit() - 0.5) * z, z]);
        g.1.push([0.0; 3].map(|_| 0.0005 + 0.0015 * rng.unit()));
        let q = [0.0; 4].map(|_| rng.unit() - 0.5);
        let norm = q.iter().map(|v| v * v).sum::<f32>().sqrt().max(1e-3);
        g.2.push(q.map(|v| v / norm));
        g.3.push(0.02 + (max_opacity - 0.02) * rng.unit());
        g.4.push([rng.unit(), rng.unit(), rng.unit()]);
    }
    GaussianSet::new(g.0, g.1, g.2, g.3, g.4).unwrap()
}

#[test]
fn the_footprints_agree_on_tiny_gaussians() {
    // With Σ2D within [0.3, 0.313]: 3DGS's λ ≤ 0.313 + √0.1, so r = 3, and the pixels its tile
    // range may leave out lie more than r − 1 = 2 pixels off centre (d² > 12.7: alpha < 1/255). Below
    // opacity e^4.5/255 ≈ 0.353 alpha falls below 1/255 before 3 sigma (d² ≤ 2 ln(255 · 0.35) =
    // 8.96), within 1.67 pixels of the centre: both footprints evaluate exactly the pixels where
    // alpha reaches 1/255.
    let set = tiny_set(4000, 5, 0.35);
    let cam = camera(128, 96, 100.0);
    for (name, r) in rasterizers() {
        let ellipse = render(r, &set, &cam, Footprint::Ellipse);
        let tiles = render(r, &set, &cam, Footprint::Tiles3dgs);
        let d = compare(&tiles, &ellipse);
        println!("{name}: {d:?}");
        assert!(ellipse.alpha.iter().filter(|&&a| a > 0.0).count() > 5000);
        assert!(
            d.rgb_max_abs <= 1e-5
                && d.alpha_max_abs <= 1e-5
                && d.depth_max_rel_where_alpha_gt_half <= 1e-5,
            "{name}: {d:?}"
        );
    }
    // Opaque, the same tiny Gaussians part: each one's fringe between 3 sigma and 1/255 (alpha up
    // to opacity · e^-4.5 ≈ 0.011, where several overlap more) is drawn by 3DGS only.
    let opaque = tiny_set(4000, 5, 1.0);
    let cpu = CpuRasterizer::new();
    let d = compare(
        &render(&cpu, &opaque, &cam, Footprint::Tiles3dgs),
        &render(&cpu, &opaque, &cam, Footprint::Ellipse),
    );
    assert!(
        d.alpha_max_abs > 1.0 / 255.0 && d.alpha_max_abs < 0.1,
        "{d:?}"
    );
}

#[test]
fn banding_the_tile_pairs_changes_nothing_with_the_3dgs_footprint() {
    let set = random_set(3000, 9, 0.8, 0.08);
    let cam = camera(160, 120, 120.0);
    let whole = render(&CpuRasterizer::new(), &set, &cam, Footprint::Tiles3dgs);
    let banded = render(
        &CpuRasterizer::new().with_pair_budget(500),
        &set,
        &cam,
        Footprint::Tiles3dgs,
    );
    assert_eq!(whole, banded);
}
