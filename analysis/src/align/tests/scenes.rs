//! Deterministic scenes for the alignment's tests: random anisotropic, randomly coloured Gaussians
//! filling a frustum slab in front of the camera, plus cameras around it.

use glam::{Affine3A, Quat, Vec3};

use c4g_scene::test_rng::{Rng, unit};
use c4g_scene::{Camera, GaussianSet, NormalizedIntrinsics};

/// `n` Gaussians at depth `near..far` in front of the identity camera, inside its view (x/z and
/// y/z within ±0.5, C4G's half-FOV tangent being 0.57), with scales `scale.0..scale.1` (world
/// units, per axis), random rotations, opacities 0.2..1 and colours in 0..1.
pub(super) fn slab(seed: u64, n: usize, depth: (f64, f64), scale: (f64, f64)) -> GaussianSet {
    let mut rng = Rng(seed);
    let mut positions = Vec::with_capacity(n);
    let mut scales = Vec::with_capacity(n);
    let mut rotations = Vec::with_capacity(n);
    let mut opacities = Vec::with_capacity(n);
    let mut colors = Vec::with_capacity(n);
    for _ in 0..n {
        let z = f64::from(rng.range(depth.0, depth.1));
        positions.push([
            rng.range(-0.5 * z, 0.5 * z),
            rng.range(-0.5 * z, 0.5 * z),
            z as f32,
        ]);
        scales.push([
            rng.range(scale.0, scale.1),
            rng.range(scale.0, scale.1),
            rng.range(scale.0, scale.1),
        ]);
        rotations.push(unit([
            rng.next() - 0.5,
            rng.next() - 0.5,
            rng.next() - 0.5,
            rng.next() - 0.5,
        ]));
        opacities.push(rng.range(0.2, 1.0));
        colors.push([
            rng.range(0.0, 1.0),
            rng.range(0.0, 1.0),
            rng.range(0.0, 1.0),
        ]);
    }
    GaussianSet::new(positions, scales, rotations, opacities, colors)
        .unwrap_or_else(|e| panic!("{e}"))
}

/// The scene for finite differences: [`slab`] plus Gaussians that reach every rule of the
/// forward model: one far outside the view whose x/z is clamped in `J` but whose footprint
/// reaches into the image, opaque wide ones whose centres clamp alpha at 0.99, and a stack that
/// reaches the transmittance floor.
pub(super) fn rules(seed: u64, n: usize) -> GaussianSet {
    let base = slab(seed, n, (1.5, 5.0), (0.02, 0.25));
    let mut gaussians: Vec<_> = base.iter().collect();
    let extra = |position: Vec3, scale: Vec3, opacity: f32, color: Vec3| c4g_scene::Gaussian {
        position,
        scale,
        rotation: Quat::from_rotation_z(0.3) * Quat::from_rotation_x(0.2),
        opacity,
        color,
    };
    // x/z = 2.5, beyond the clamp at 1.3 × 0.57 = 0.74, but 1.2 wide at depth 1: it shows.
    gaussians.push(extra(
        Vec3::new(2.5, 0.1, 1.0),
        Vec3::new(1.2, 0.4, 0.3),
        0.9,
        Vec3::new(0.9, 0.2, 0.1),
    ));
    for k in 0..6 {
        gaussians.push(extra(
            Vec3::new(-0.3 + 0.02 * k as f32, 0.2, 2.0 + 0.1 * k as f32),
            Vec3::new(0.3, 0.25, 0.2),
            1.0,
            Vec3::new(0.1 * k as f32, 0.8, 0.5),
        ));
    }
    GaussianSet::from_gaussians(gaussians)
}

/// C4G's default intrinsics at `width` × `height`, posed by `world_to_camera`.
pub(super) fn camera(width: u32, height: u32, world_to_camera: Affine3A) -> Camera {
    Camera::from_normalized(
        NormalizedIntrinsics::C4G_DEFAULT,
        width,
        height,
        world_to_camera,
    )
    .unwrap_or_else(|e| panic!("{e}"))
}

/// A camera looking at the slab from off its axis: turned by a few degrees and moved.
pub(super) fn oblique() -> Affine3A {
    Affine3A::from_rotation_translation(
        Quat::from_rotation_y(0.06) * Quat::from_rotation_x(-0.04) * Quat::from_rotation_z(0.05),
        Vec3::new(0.1, -0.05, 0.2),
    )
}
