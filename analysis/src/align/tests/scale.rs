//! The translation-scale fit on a synthetic scene: frames rendered by the CPU rasterizer at
//! cameras whose translations are a known factor of the given ones.
//!
//! Bounds, and why: the targets are the same rasterizer's renders, so the cost's minimum is the
//! true factor exactly; the golden-section search ends within about 0.002 octave of it, and the
//! bound (0.01 octave) leaves room for the f32 round trip of the cameras.

use glam::{Affine3A, Quat, Vec3};

use super::alignment::target;
use super::scenes::{camera, slab};
use crate::align::{REFINEMENTS, STEPS, ScaleView, fit_translation_scale};
use c4g_renderer::raster::RenderOptions;
use c4g_scene::SceneError;

/// Three later context cameras of a camera moving right and a little forward while it turns.
fn given() -> Vec<Affine3A> {
    [(0.3, 0.0, 0.02), (0.6, 0.1, 0.05), (1.0, 0.1, 0.1)]
        .into_iter()
        .enumerate()
        .map(|(k, (x, y, z))| {
            Affine3A::from_rotation_translation(
                Quat::from_rotation_y(-0.03 * (k + 1) as f32),
                Vec3::new(x, y, z),
            )
        })
        .collect()
}

fn scaled(pose: Affine3A, factor: f32) -> Affine3A {
    Affine3A::from_mat3_translation(pose.matrix3.into(), Vec3::from(pose.translation) * factor)
}

#[test]
fn finds_the_factor_that_made_the_frames() {
    let set = slab(7, 400, (2.0, 6.0), (0.03, 0.2));
    let options = RenderOptions::default();
    for truth in [0.3_f32, 1.0, 4.0] {
        let targets: Vec<_> = given()
            .into_iter()
            .map(|pose| target(&set, &camera(64, 64, scaled(pose, truth)), &options))
            .collect();
        let views: Vec<_> = given()
            .into_iter()
            .zip(&targets)
            .map(|(pose, target)| ScaleView {
                set: &set,
                target,
                camera: camera(64, 64, pose),
            })
            .collect();
        let fit = fit_translation_scale(&views, &options).unwrap_or_else(|e| panic!("{e}"));
        assert!(
            (fit.factor / f64::from(truth)).log2().abs() < 0.01,
            "{truth}: {fit:?}"
        );
        assert!(fit.error <= fit.initial_error);
        if truth == 1.0 {
            assert_eq!(fit.factor, 1.0, "no better factor than 1: it stays 1");
        } else {
            assert!(fit.error < 1e-3 * fit.initial_error, "{fit:?}");
        }
        let per_view = STEPS.count() + 2 + REFINEMENTS;
        assert_eq!(fit.evaluations, 3 * per_view);
    }
}

#[test]
fn cameras_that_do_not_move_keep_the_factor_one() {
    let set = slab(8, 200, (2.0, 6.0), (0.03, 0.2));
    let options = RenderOptions::default();
    let pose = Affine3A::from_quat(Quat::from_rotation_y(0.05));
    let frame = target(&set, &camera(64, 64, pose), &options);
    let views = [ScaleView {
        set: &set,
        target: &frame,
        camera: camera(64, 64, pose),
    }];
    let fit = fit_translation_scale(&views, &options).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(fit.factor, 1.0);
}

#[test]
fn a_frame_of_the_wrong_size_is_refused() {
    let set = slab(9, 10, (2.0, 6.0), (0.03, 0.2));
    let frame = vec![0.5_f32; 3 * 32 * 32];
    let views = [ScaleView {
        set: &set,
        target: &frame,
        camera: camera(64, 64, Affine3A::IDENTITY),
    }];
    let err = fit_translation_scale(&views, &RenderOptions::default()).unwrap_err();
    assert!(matches!(err, SceneError::InvalidImage(_)), "{err}");
}
