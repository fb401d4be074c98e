//! The camera Jacobian of a render (`c4g_analysis::align::camera_jacobian`) on the fixture scenes
//! of `models/fixtures/scenes/` (both footprints):
//! - its f64 render is the float64 reference's, to 1e-6 in RGB and alpha: the same forward model
//!   in the same precision on the same (f32-rounded) inputs, the scenes kept clear of the model's
//!   steps by the generator's margins; what is left is the f32 storage of the expected images
//!   (measured: at most 5.5e-8);
//! - its gradient of a quadratic per-pixel loss matches central finite differences of the same
//!   f64 render with h = 1e-7, within 2e-6 of the gradient's largest component (the step and
//!   tolerance are argued in `analysis/src/align/tests/jacobian.rs`; measured here: at most
//!   1.4e-7, on gradients of 300 to 2,200).
//!   The margins that keep the scenes' pixels away from the 3-sigma cut, the 1/255 floor and the
//!   transmittance stop (1e-4 relative) are also what keep a step of 1e-7 from crossing one.
#![allow(clippy::unwrap_used, clippy::expect_used)]

// The renderer's test helpers (fixture scenes, cameras, random sets), shared rather than copied.
#[path = "../../renderer/tests/common/mod.rs"]
mod common;

use c4g_analysis::align::{
    CAMERA_PARAMETER_NAMES, CAMERA_PARAMETERS, CameraAdjustment, camera_jacobian,
};
use c4g_renderer::RenderOptions;
use c4g_scene::{Camera, GaussianSet};
use common::*;

const H: f64 = 1e-7;

/// `½ Σ (rgb − 0.5)² + ½ Σ (alpha − 0.3)²` and its analytic gradient at `at ∘ camera`.
fn loss(
    set: &GaussianSet,
    camera: &Camera,
    at: &CameraAdjustment,
    options: &RenderOptions,
) -> (f64, [f64; CAMERA_PARAMETERS]) {
    let j = camera_jacobian(set, camera, at, options).unwrap();
    let d_rgb: Vec<f64> = j.rgb.iter().map(|v| v - 0.5).collect();
    let d_alpha: Vec<f64> = j.alpha.iter().map(|v| v - 0.3).collect();
    let value = 0.5 * d_rgb.iter().chain(&d_alpha).map(|r| r * r).sum::<f64>();
    (value, j.gradient(&d_rgb, Some(&d_alpha)).unwrap())
}

#[test]
fn the_f64_render_matches_the_float64_reference_on_every_fixture_scene() {
    for name in SCENES.iter().chain(&SCENES_3DGS) {
        let scene = load_scene(name);
        let j = camera_jacobian(
            &scene.gaussians,
            &scene.camera,
            &CameraAdjustment::IDENTITY,
            &scene.options,
        )
        .unwrap();
        let worst = |a: &[f64], b: &[f32]| {
            a.iter()
                .zip(b)
                .map(|(x, y)| (x - f64::from(*y)).abs())
                .fold(0.0, f64::max)
        };
        let (rgb, alpha) = (
            worst(&j.rgb, &scene.expected.rgb),
            worst(&j.alpha, &scene.expected.alpha),
        );
        eprintln!("{name}: rgb {rgb:.2e}, alpha {alpha:.2e} from the reference");
        assert!(
            rgb <= 1e-6 && alpha <= 1e-6,
            "{name}: rgb {rgb:.2e}, alpha {alpha:.2e}"
        );
    }
}

#[test]
fn the_gradient_matches_finite_differences_on_fixture_scenes() {
    for name in [
        "cloud",
        "large",
        "stack",
        "cloud-3dgs",
        "large-3dgs",
        "stack-3dgs",
    ] {
        let scene = load_scene(name);
        let (set, camera, options) = (&scene.gaussians, &scene.camera, &scene.options);
        let at = CameraAdjustment::IDENTITY;
        let (_, analytic) = loss(set, camera, &at, options);
        let scale = analytic.iter().fold(0.0f64, |m, g| m.max(g.abs()));
        let mut worst = 0.0f64;
        for k in 0..CAMERA_PARAMETERS {
            let mut step = [0.0; CAMERA_PARAMETERS];
            step[k] = H;
            let plus = loss(set, camera, &at.then(&CameraAdjustment::exp(step)), options).0;
            step[k] = -H;
            let minus = loss(set, camera, &at.then(&CameraAdjustment::exp(step)), options).0;
            let numeric = (plus - minus) / (2.0 * H);
            let error = (numeric - analytic[k]).abs() / scale;
            worst = worst.max(error);
            assert!(
                error <= 2e-6,
                "{name}, {}: analytic {} vs finite differences {numeric} ({error:.2e})",
                CAMERA_PARAMETER_NAMES[k],
                analytic[k]
            );
        }
        eprintln!("{name}: worst relative error {worst:.2e} (gradient scale {scale:.1})");
    }
}
