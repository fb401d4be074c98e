//! Camera recovery on synthetic scenes with known cameras: a target rendered by the CPU
//! rasterizer at the true camera, alignment started from a perturbed one (3° about an oblique
//! axis, 5% of the scene's mean depth of 4 in translation), defaults unless a test says.
//!
//! Bounds, and why: the target is the f32 rasterizer's render and the alignment's model its f64
//! restatement, which agree to ~1e-6 per pixel, so an exact recovery is possible up to that
//! noise; the bounds (0.05° in rotation, 0.005 scene units, an eighth of a percent of the depth,
//! for the camera centre, a residual a thousandth of the start's) leave room for the f32 round
//! trip of the camera and the last steps' tolerance, and are an order of magnitude below what a
//! pixel of error at 64² would be (a pixel is ~1° there).

use glam::{Affine3A, Vec3};

use super::scenes::{camera, oblique, slab};
use crate::align::{AlignOptions, Alignment, CameraAdjustment, align_camera};
use c4g_renderer::raster::RenderOptions;
use c4g_renderer::{CpuRasterizer, Rasterizer};
use c4g_scene::Footprint;
use c4g_scene::{Camera, GaussianSet, SceneError};

/// 3° about an oblique axis and 0.2 (5% of the mean depth 4) along another, and a focal scale.
pub(super) fn perturbation(log_focal: f64) -> CameraAdjustment {
    let axis = Vec3::new(0.6, -0.7, 0.4).normalize().as_dvec3() * 3f64.to_radians();
    let shift = Vec3::new(-0.5, 0.3, 0.8).normalize().as_dvec3() * 0.2;
    CameraAdjustment::exp([axis.x, axis.y, axis.z, shift.x, shift.y, shift.z, log_focal])
}

pub(super) fn target(set: &GaussianSet, camera: &Camera, options: &RenderOptions) -> Vec<f32> {
    CpuRasterizer::new()
        .render(set, camera, options)
        .unwrap_or_else(|e| panic!("{e}"))
        .rgb
}

/// Rotation error in degrees (the angle of `R_got R_truthᵀ`, in f64 from its skew part and
/// trace, exact for small angles) and camera-centre error in scene units.
pub(super) fn pose_error(got: &Camera, truth: &Camera) -> (f64, f64) {
    let rotation = |c: &Camera| {
        let m = c.world_to_camera().matrix3;
        glam::DMat3::from_cols(
            m.x_axis.as_dvec3(),
            m.y_axis.as_dvec3(),
            m.z_axis.as_dvec3(),
        )
    };
    let r = rotation(got) * rotation(truth).transpose();
    let skew = glam::DVec3::new(
        r.y_axis.z - r.z_axis.y,
        r.z_axis.x - r.x_axis.z,
        r.x_axis.y - r.y_axis.x,
    ) * 0.5;
    let cos = 0.5 * (r.x_axis.x + r.y_axis.y + r.z_axis.z - 1.0);
    let angle = skew.length().atan2(cos).to_degrees();
    let centre = (got.position().as_dvec3() - truth.position().as_dvec3()).length();
    (angle, centre)
}

fn align(
    set: &GaussianSet,
    truth: &Camera,
    start: &Camera,
    options: &AlignOptions,
) -> (Alignment, f64, f64) {
    let target = target(set, truth, &options.render);
    let alignment = align_camera(set, &target, start, options).unwrap_or_else(|e| panic!("{e}"));
    let (rotation, centre) = pose_error(&alignment.camera, truth);
    eprintln!(
        "rotation error {rotation:.4}°, centre error {centre:.5}, residual {:.3e} → {:.3e}, \
         {} iterations, converged {}, confidence {:.3} (coverage {:.3}, conditioning {:.2e})",
        alignment.initial_residual,
        alignment.residual,
        alignment.iterations,
        alignment.converged,
        alignment.confidence,
        alignment.coverage,
        alignment.conditioning,
    );
    (alignment, rotation, centre)
}

fn assert_recovered(alignment: &Alignment, rotation: f64, centre: f64) {
    assert!(rotation < 0.05, "rotation error {rotation}°");
    assert!(centre < 0.005, "centre error {centre}");
    assert!(alignment.residual < 1e-3 * alignment.initial_residual);
    assert!(alignment.converged);
    assert!(alignment.confidence > 0.5, "{}", alignment.confidence);
}

#[test]
fn a_perturbed_camera_is_recovered_at_64_pixels() {
    let set = slab(11, 400, (2.0, 6.0), (0.03, 0.15));
    let truth = camera(64, 64, oblique());
    let start = perturbation(0.0)
        .apply(&truth)
        .unwrap_or_else(|e| panic!("{e}"));
    let (before, _) = pose_error(&start, &truth);
    assert!((before - 3.0).abs() < 1e-3);
    let (alignment, rotation, centre) = align(&set, &truth, &start, &AlignOptions::default());
    assert_recovered(&alignment, rotation, centre);
}

#[test]
fn a_perturbed_camera_is_recovered_at_224_pixels_with_the_defaults() {
    // C4G's input size and Gaussian count, splats of 1 to 4 pixels.
    let set = slab(18, 2048, (2.0, 6.0), (0.015, 0.08));
    let truth = camera(224, 224, oblique());
    let start = perturbation(0.0)
        .apply(&truth)
        .unwrap_or_else(|e| panic!("{e}"));
    let (alignment, rotation, centre) = align(&set, &truth, &start, &AlignOptions::default());
    assert_recovered(&alignment, rotation, centre);
}

#[test]
fn a_perturbed_camera_is_recovered_with_the_3dgs_footprint_over_a_background() {
    let set = slab(12, 400, (2.0, 6.0), (0.03, 0.15));
    let truth = camera(96, 72, oblique());
    let start = perturbation(0.0)
        .apply(&truth)
        .unwrap_or_else(|e| panic!("{e}"));
    let options = AlignOptions {
        render: RenderOptions {
            footprint: Footprint::Tiles3dgs,
            background: [0.3, 0.3, 0.35],
            ..RenderOptions::default()
        },
        ..AlignOptions::default()
    };
    let (alignment, rotation, centre) = align(&set, &truth, &start, &options);
    assert_recovered(&alignment, rotation, centre);
}

#[test]
fn the_focal_length_is_recovered_when_asked() {
    let set = slab(13, 400, (2.0, 6.0), (0.03, 0.15));
    let truth = camera(64, 64, oblique());
    // 5% too long a focal length on top of the pose's perturbation.
    let start = perturbation(0.05f64.ln_1p())
        .apply(&truth)
        .unwrap_or_else(|e| panic!("{e}"));
    let options = AlignOptions {
        refine_focal: true,
        ..AlignOptions::default()
    };
    let (alignment, rotation, centre) = align(&set, &truth, &start, &options);
    assert_recovered(&alignment, rotation, centre);
    let focal = alignment.camera.intrinsics().fx / truth.intrinsics().fx;
    assert!((focal - 1.0).abs() < 1e-3, "focal ratio {focal}");
    assert_eq!(
        alignment.camera.intrinsics().fx,
        alignment.camera.intrinsics().fy
    );
}

#[test]
fn a_patch_the_set_does_not_explain_is_outvoted() {
    // A 14×14 block of flat colour (5% of the frame) over the target: something in the frame
    // the set does not explain. Huber's linear tail bounds its pull.
    let set = slab(17, 400, (2.0, 6.0), (0.03, 0.15));
    let truth = camera(64, 64, oblique());
    let start = perturbation(0.0)
        .apply(&truth)
        .unwrap_or_else(|e| panic!("{e}"));
    let options = AlignOptions::default();
    let mut frame = target(&set, &truth, &options.render);
    for y in 20..34 {
        for x in 36..50 {
            frame[3 * (y * 64 + x)..3 * (y * 64 + x) + 3].copy_from_slice(&[1.0, 0.0, 1.0]);
        }
    }
    let alignment = align_camera(&set, &frame, &start, &options).unwrap_or_else(|e| panic!("{e}"));
    let (rotation, centre) = pose_error(&alignment.camera, &truth);
    eprintln!("occluded: rotation error {rotation:.4}°, centre error {centre:.5}, {alignment:?}");
    assert!(rotation < 0.1, "rotation error {rotation}°");
    assert!(centre < 0.01, "centre error {centre}");
}

#[test]
fn starting_at_the_true_camera_stays_there() {
    let set = slab(14, 400, (2.0, 6.0), (0.03, 0.15));
    let truth = camera(64, 64, oblique());
    let (alignment, rotation, centre) = align(&set, &truth, &truth, &AlignOptions::default());
    assert!(rotation < 0.005, "rotation error {rotation}°");
    assert!(centre < 5e-4, "centre error {centre}");
    assert!(alignment.converged);
    assert!(alignment.confidence > 0.5, "{}", alignment.confidence);
}

#[test]
fn a_set_outside_the_view_gives_zero_confidence_and_leaves_the_camera() {
    let set = slab(15, 100, (2.0, 6.0), (0.03, 0.15));
    let truth = camera(64, 64, oblique());
    let target = target(&set, &truth, &RenderOptions::default());
    // Turned 180° about y: every Gaussian is behind it.
    let away = Affine3A::from_rotation_y(std::f32::consts::PI) * oblique();
    let start = camera(64, 64, away);
    let alignment = align_camera(&set, &target, &start, &AlignOptions::default())
        .unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(alignment.confidence, 0.0);
    assert_eq!(alignment.coverage, 0.0);
    assert_eq!(alignment.iterations, 0);
    assert_eq!(alignment.camera, start);
}

#[test]
fn a_single_round_splat_gives_low_confidence() {
    // One round blob: a turn and a sideways shift of the camera look alike.
    let set = GaussianSet::new(
        vec![[0.1, -0.1, 3.0]],
        vec![[0.3; 3]],
        vec![[1.0, 0.0, 0.0, 0.0]],
        vec![0.9],
        vec![[0.8, 0.5, 0.2]],
    )
    .unwrap_or_else(|e| panic!("{e}"));
    let truth = camera(64, 64, Affine3A::IDENTITY);
    let start = perturbation(0.0)
        .apply(&truth)
        .unwrap_or_else(|e| panic!("{e}"));
    let target = target(&set, &truth, &RenderOptions::default());
    let alignment = align_camera(&set, &target, &start, &AlignOptions::default())
        .unwrap_or_else(|e| panic!("{e}"));
    eprintln!("single splat: {alignment:?}");
    assert!(alignment.confidence < 0.01, "{}", alignment.confidence);
    assert!(alignment.camera.world_to_camera().is_finite());
}

#[test]
fn bad_inputs_are_refused_with_what_to_fix() {
    let set = slab(16, 20, (2.0, 6.0), (0.03, 0.15));
    let cam = camera(32, 32, Affine3A::IDENTITY);
    let good = vec![0.5f32; 32 * 32 * 3];
    let options = AlignOptions::default();
    let message = |r: Result<Alignment, SceneError>| match r {
        Err(e) => e.to_string(),
        Ok(a) => panic!("accepted: {a:?}"),
    };
    let wrong_size = message(align_camera(&set, &good[3..], &cam, &options));
    assert!(wrong_size.contains("32x32"), "{wrong_size}");
    let empty = message(align_camera(&GaussianSet::default(), &good, &cam, &options));
    assert!(empty.contains("empty"), "{empty}");
    let mut nan = good.clone();
    nan[7] = f32::NAN;
    let nan = message(align_camera(&set, &nan, &cam, &options));
    assert!(nan.contains("pixel 2"), "{nan}");
    for broken in [
        AlignOptions {
            huber_delta: 0.0,
            ..AlignOptions::default()
        },
        AlignOptions {
            max_iterations: 0,
            ..AlignOptions::default()
        },
        AlignOptions {
            levels: Some(0),
            ..AlignOptions::default()
        },
        AlignOptions {
            tolerance: f64::NAN,
            ..AlignOptions::default()
        },
    ] {
        assert!(matches!(
            align_camera(&set, &good, &cam, &broken),
            Err(SceneError::InvalidRenderOptions(_))
        ));
    }
}
