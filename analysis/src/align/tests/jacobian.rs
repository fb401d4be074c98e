//! The camera Jacobian against central finite differences of the same f64 render, and its
//! invariants.
//!
//! The loss is `L = ½ Σ (rgb − target)² + ½ Σ (alpha − target alpha)²` against a fixed random
//! target, its gradient chained through [`CameraJacobian::gradient`]. The step is h = 1e-7 for
//! every parameter (radians, scene units at depths 1..5, log focal: all of order one). Why that
//! small: the render is piecewise smooth (3-sigma cut, 1/255 floor, transmittance stop, depth
//! order), and a step that moves any (pixel, splat) pair across one of those jumps ruins the
//! difference; at 1e-7 a splat moves by ~1e-5 pixels, so few of the ~10⁴ pairs of these scenes
//! can be that close to an edge (the seeds are fixed, and none is). Why not smaller: the
//! difference's rounding is ~ε·|L| / h ≈ 1e-16 · 10³ / 1e-7 ≈ 1e-6 absolute, while its
//! truncation error is ~h² · L‴ ≈ 1e-11 relative; a kink (the 0.99 alpha clamp) inside a step
//! adds O(h). The tolerance, 2e-6 of the gradient's largest component, per component: the worst
//! measured is 1.4e-7, and removing one term of the chain rule shows as 2e-5 to 5e-3 (tried:
//! the FOV clamp's zero, the alpha clamp's zero, the clamp limit's focal dependence).

use glam::Affine3A;

use super::scenes::{camera, oblique, rules, slab};
use crate::align::{CAMERA_PARAMETER_NAMES, CAMERA_PARAMETERS, CameraAdjustment, camera_jacobian};
use c4g_renderer::raster::RenderOptions;
use c4g_renderer::{CpuRasterizer, Rasterizer};
use c4g_scene::Footprint;
use c4g_scene::test_rng::Rng;
use c4g_scene::{Camera, GaussianSet};

const H: f64 = 1e-7;
const TOLERANCE: f64 = 2e-6;

fn options(footprint: Footprint) -> RenderOptions {
    RenderOptions {
        background: [0.2, 0.4, 0.1],
        footprint,
        ..RenderOptions::default()
    }
}

/// A random target image: RGB and alpha in 0..1.
fn target(seed: u64, pixels: usize) -> (Vec<f64>, Vec<f64>) {
    let mut rng = Rng(seed);
    let rgb = (0..3 * pixels).map(|_| rng.next()).collect();
    let alpha = (0..pixels).map(|_| rng.next()).collect();
    (rgb, alpha)
}

/// `L` at `adjustment ∘ camera`, and its analytic gradient there.
fn loss(
    set: &GaussianSet,
    camera: &Camera,
    adjustment: &CameraAdjustment,
    options: &RenderOptions,
    (rgb, alpha): &(Vec<f64>, Vec<f64>),
) -> (f64, [f64; CAMERA_PARAMETERS]) {
    let j = camera_jacobian(set, camera, adjustment, options).unwrap_or_else(|e| panic!("{e}"));
    let d_rgb: Vec<f64> = j.rgb.iter().zip(rgb).map(|(a, b)| a - b).collect();
    let d_alpha: Vec<f64> = j.alpha.iter().zip(alpha).map(|(a, b)| a - b).collect();
    let value = 0.5 * d_rgb.iter().chain(&d_alpha).map(|r| r * r).sum::<f64>();
    let grad = j
        .gradient(&d_rgb, Some(&d_alpha))
        .unwrap_or_else(|e| panic!("{e}"));
    (value, grad)
}

/// Holds the analytic gradient to central differences for all seven parameters; returns the
/// largest error relative to the gradient's largest component.
fn check_against_finite_differences(
    name: &str,
    set: &GaussianSet,
    camera: &Camera,
    at: &CameraAdjustment,
    options: &RenderOptions,
) -> f64 {
    let pixels = (camera.width() * camera.height()) as usize;
    let target = target(7, pixels);
    let (_, analytic) = loss(set, camera, at, options, &target);
    let scale = analytic.iter().fold(0.0f64, |m, g| m.max(g.abs()));
    assert!(scale > 1.0, "{name}: the scene should move with the camera");
    let mut worst = 0.0f64;
    for k in 0..CAMERA_PARAMETERS {
        let mut step = [0.0; CAMERA_PARAMETERS];
        step[k] = H;
        let plus = at.then(&CameraAdjustment::exp(step));
        step[k] = -H;
        let minus = at.then(&CameraAdjustment::exp(step));
        let numeric = (loss(set, camera, &plus, options, &target).0
            - loss(set, camera, &minus, options, &target).0)
            / (2.0 * H);
        let error = (numeric - analytic[k]).abs() / scale;
        assert!(
            error <= TOLERANCE,
            "{name}, {}: analytic {} vs finite differences {numeric} (relative error {error:.2e})",
            CAMERA_PARAMETER_NAMES[k],
            analytic[k],
        );
        worst = worst.max(error);
    }
    worst
}

#[test]
fn the_f64_render_is_the_cpu_rasterizers_forward_model() {
    for footprint in [Footprint::Ellipse, Footprint::Tiles3dgs] {
        let options = options(footprint);
        let set = rules(3, 300);
        let camera = camera(80, 60, oblique());
        let j = camera_jacobian(&set, &camera, &CameraAdjustment::IDENTITY, &options)
            .unwrap_or_else(|e| panic!("{e}"));
        let image = CpuRasterizer::new()
            .render(&set, &camera, &options)
            .unwrap_or_else(|e| panic!("{e}"));
        let max_diff = |a: &[f64], b: &[f32]| {
            a.iter()
                .zip(b)
                .map(|(x, y)| (x - f64::from(*y)).abs())
                .fold(0.0, f64::max)
        };
        // The rasterizers' reference tolerance (renderer/tests/common/mod.rs).
        assert!(max_diff(&j.rgb, &image.rgb) <= 2e-3, "{footprint}");
        assert!(max_diff(&j.alpha, &image.alpha) <= 2e-3, "{footprint}");
    }
}

#[test]
fn the_gradient_matches_finite_differences_for_both_footprints() {
    for footprint in [Footprint::Ellipse, Footprint::Tiles3dgs] {
        for seed in [1, 2] {
            let name = format!("{footprint}, seed {seed}");
            let worst = check_against_finite_differences(
                &name,
                &rules(seed, 200),
                &camera(64, 48, Affine3A::IDENTITY),
                &CameraAdjustment::IDENTITY,
                &options(footprint),
            );
            eprintln!("{name}: worst relative error {worst:.2e}");
        }
    }
}

#[test]
fn the_gradient_matches_finite_differences_at_an_adjusted_oblique_camera() {
    // Away from the identity adjustment, with a scaled focal length and fx ≠ fy.
    let mut camera = camera(72, 56, oblique());
    let mut k = *camera.intrinsics();
    k.fy *= 1.1;
    k.cx += 3.0;
    camera = Camera::new(k, camera.world_to_camera()).unwrap_or_else(|e| panic!("{e}"));
    let at = CameraAdjustment::exp([0.02, -0.03, 0.01, 0.05, -0.02, 0.1, 0.04]);
    for footprint in [Footprint::Ellipse, Footprint::Tiles3dgs] {
        check_against_finite_differences(
            &format!("oblique, {footprint}"),
            &rules(5, 250),
            &camera,
            &at,
            &options(footprint),
        );
    }
}

#[test]
fn zero_gaussians_give_the_background_and_a_zero_gradient() {
    let empty = GaussianSet::default();
    let camera = camera(40, 30, Affine3A::IDENTITY);
    let options = options(Footprint::Ellipse);
    let j = camera_jacobian(&empty, &camera, &CameraAdjustment::IDENTITY, &options)
        .unwrap_or_else(|e| panic!("{e}"));
    assert!(
        j.rgb
            .chunks(3)
            .all(|p| p == [0.2f32, 0.4, 0.1].map(f64::from))
    );
    assert!(j.alpha.iter().all(|&a| a == 0.0));
    assert!(
        j.d_rgb
            .iter()
            .chain(&j.d_alpha)
            .flatten()
            .all(|&d| d == 0.0)
    );
}

#[test]
fn a_gaussian_outside_the_image_changes_nothing() {
    let camera = camera(64, 48, Affine3A::IDENTITY);
    let base = slab(4, 100, (2.0, 5.0), (0.02, 0.2));
    let mut with: Vec<_> = base.iter().collect();
    let mut outside = with[0];
    // Beside the view (x/z = 3, small), and behind the camera.
    outside.position = glam::Vec3::new(6.0, 0.0, 2.0);
    outside.scale = glam::Vec3::splat(0.05);
    with.push(outside);
    outside.position = glam::Vec3::new(0.0, 0.0, -2.0);
    with.push(outside);
    let with = GaussianSet::from_gaussians(with);
    for footprint in [Footprint::Ellipse, Footprint::Tiles3dgs] {
        let options = options(footprint);
        let at = CameraAdjustment::exp([0.01, 0.0, 0.0, 0.0, 0.02, 0.0, 0.0]);
        let a = camera_jacobian(&base, &camera, &at, &options).unwrap_or_else(|e| panic!("{e}"));
        let b = camera_jacobian(&with, &camera, &at, &options).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(a, b, "{footprint}");
    }
}

#[test]
fn the_gradient_refuses_derivatives_of_the_wrong_size_and_non_finite_adjustments() {
    let camera = camera(16, 16, Affine3A::IDENTITY);
    let set = slab(1, 10, (2.0, 3.0), (0.05, 0.1));
    let options = options(Footprint::Ellipse);
    let j = camera_jacobian(&set, &camera, &CameraAdjustment::IDENTITY, &options)
        .unwrap_or_else(|e| panic!("{e}"));
    assert!(j.gradient(&[0.0; 3], None).is_err());
    assert!(
        j.gradient(&vec![0.0; 16 * 16 * 3], Some(&[0.0; 2]))
            .is_err()
    );
    let nan = CameraAdjustment::exp([f64::NAN, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]);
    assert!(camera_jacobian(&set, &camera, &nan, &options).is_err());
}
