//! The CPU rasterizer's backward pass, held to central finite differences of an independent
//! float64 forward model (written here, dense: every Gaussian at every pixel) and to the
//! properties any gradient of this forward model must have.
//!
//! Why finite differences of a *float64* model: the render is only piecewise smooth (the 3-sigma
//! or tile edge, the 1/255 skip, the alpha clamp, the transmittance stop); a step that moves a
//! (pixel, Gaussian) pair across one of them measures the jump, not the derivative. With f64 and
//! steps of 1e-6 crossings are rare, and every one is detected (the composited pairs of both
//! perturbed renders are hashed and compared with the unperturbed render's) and that component
//! is left out; the tests require that almost all components are checked.
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use c4g_renderer::raster::{TRANSMITTANCE_MIN, tiles_3dgs};
use c4g_renderer::{
    BackwardOptions, CpuRasterizer, DifferentiableRasterizer, Gradients, Rasterizer,
    RenderGradients, RenderOptions,
};
use c4g_scene::{Camera, Footprint, GaussianSet, Intrinsics};
use common::SplitMix;
use glam::{Affine3A, DMat3, DVec3, Quat, Vec3};

// ---------------------------------------------------------------------------------------------
// The float64 dense forward model (independent of the crate's tiles, boxes and f32 arithmetic).

/// One Gaussian in the optimiser's parametrisation, f64.
#[derive(Debug, Clone, Copy)]
struct Params {
    position: [f64; 3],
    log_scale: [f64; 3],
    rotation: [f64; 4],
    opacity_logit: f64,
    color: [f64; 3],
}

impl Params {
    fn from_set(set: &GaussianSet) -> Vec<Self> {
        (0..set.len())
            .map(|i| {
                let o = f64::from(set.opacities()[i]);
                Self {
                    position: set.positions()[i].map(f64::from),
                    log_scale: set.scales()[i].map(|s| f64::from(s).ln()),
                    rotation: set.rotations()[i].map(f64::from),
                    opacity_logit: (o / (1.0 - o)).ln(),
                    color: set.colors()[i].map(f64::from),
                }
            })
            .collect()
    }

    fn get(&self, k: usize) -> f64 {
        match k {
            0..3 => self.position[k],
            3..6 => self.log_scale[k - 3],
            6..10 => self.rotation[k - 6],
            10 => self.opacity_logit,
            _ => self.color[k - 11],
        }
    }

    fn set(&mut self, k: usize, v: f64) {
        match k {
            0..3 => self.position[k] = v,
            3..6 => self.log_scale[k - 3] = v,
            6..10 => self.rotation[k - 6] = v,
            10 => self.opacity_logit = v,
            _ => self.color[k - 11] = v,
        }
    }
}

/// The camera in f64 with a tangent `[ω, ν, log focal]` applied (left increment).
struct View64 {
    rotation: DMat3,
    translation: DVec3,
    fx: f64,
    fy: f64,
    cx: f64,
    cy: f64,
    width: u32,
    height: u32,
}

fn rodrigues(w: DVec3) -> DMat3 {
    let theta = w.length();
    if theta == 0.0 {
        return DMat3::IDENTITY;
    }
    DMat3::from_axis_angle(w / theta, theta)
}

impl View64 {
    fn new(camera: &Camera, tangent: [f64; 7]) -> Self {
        let pose = camera.world_to_camera();
        let w = DMat3::from_cols(
            pose.matrix3.x_axis.as_dvec3(),
            pose.matrix3.y_axis.as_dvec3(),
            pose.matrix3.z_axis.as_dvec3(),
        );
        let t = pose.translation.as_dvec3();
        let r = rodrigues(DVec3::new(tangent[0], tangent[1], tangent[2]));
        let nu = DVec3::new(tangent[3], tangent[4], tangent[5]);
        let k = camera.intrinsics();
        let focal = tangent[6].exp();
        Self {
            rotation: r * w,
            translation: r * t + nu,
            fx: f64::from(k.fx) * focal,
            fy: f64::from(k.fy) * focal,
            cx: f64::from(k.cx),
            cy: f64::from(k.cy),
            width: k.width,
            height: k.height,
        }
    }
}

fn quat_matrix(q: [f64; 4]) -> DMat3 {
    let n = q.iter().map(|v| v * v).sum::<f64>().sqrt();
    let [w, x, y, z] = q.map(|v| v / n);
    // Rows of R, transposed into glam's columns.
    DMat3::from_cols_array_2d(&[
        [
            1.0 - 2.0 * (y * y + z * z),
            2.0 * (x * y - w * z),
            2.0 * (x * z + w * y),
        ],
        [
            2.0 * (x * y + w * z),
            1.0 - 2.0 * (x * x + z * z),
            2.0 * (y * z - w * x),
        ],
        [
            2.0 * (x * z - w * y),
            2.0 * (y * z + w * x),
            1.0 - 2.0 * (x * x + y * y),
        ],
    ])
    .transpose()
}

/// A projected Gaussian of the dense model.
struct Splat64 {
    index: usize,
    z: f64,
    u: f64,
    v: f64,
    conic: [f64; 3],
    opacity: f64,
    color: [f64; 3],
    /// Inclusive pixel box of the 3DGS tiles (the ellipse: the whole image).
    bounds: [(u32, u32); 2],
}

/// The dense model's render: rgb, alpha, expected depth, and a hash of every composited (pixel,
/// Gaussian, clamped) triple in order.
struct Render64 {
    rgb: Vec<f64>,
    alpha: Vec<f64>,
    expected_depth: Vec<f64>,
    pairs: u64,
}

fn render64(
    params: &[Params],
    view: &View64,
    footprint: Footprint,
    background: [f64; 3],
) -> Render64 {
    let (near, far) = (0.01, 100.0);
    let mut splats = Vec::new();
    for (index, g) in params.iter().enumerate() {
        let opacity = 1.0 / (1.0 + (-g.opacity_logit).exp());
        if opacity < 1.0 / 255.0 {
            continue;
        }
        let p = view.rotation * DVec3::from_array(g.position) + view.translation;
        if !(p.z >= near && p.z <= far) {
            continue;
        }
        let lim_x = 1.3 * f64::from(view.width) / (2.0 * view.fx);
        let lim_y = 1.3 * f64::from(view.height) / (2.0 * view.fy);
        let tx = (p.x / p.z).clamp(-lim_x, lim_x) * p.z;
        let ty = (p.y / p.z).clamp(-lim_y, lim_y) * p.z;
        // J as a 3x3 with a zero last row, so plain matrix products give Σ2D.
        let j = DMat3::from_cols_array_2d(&[
            [view.fx / p.z, 0.0, -view.fx * tx / (p.z * p.z)],
            [0.0, view.fy / p.z, -view.fy * ty / (p.z * p.z)],
            [0.0, 0.0, 0.0],
        ])
        .transpose();
        let s = DMat3::from_diagonal(DVec3::from_array(g.log_scale.map(f64::exp)));
        let rs = quat_matrix(g.rotation) * s;
        let cov3 = rs * rs.transpose();
        let cov2 = j * view.rotation * cov3 * view.rotation.transpose() * j.transpose();
        let (mxx, mxy, myy) = (cov2.x_axis.x, cov2.y_axis.x, cov2.y_axis.y);
        let (a, b, c) = (mxx + 0.3, mxy, myy + 0.3);
        let det = a * c - b * b;
        if det <= 0.0 {
            continue;
        }
        let u = view.fx * p.x / p.z + view.cx;
        let v = view.fy * p.y / p.z + view.cy;
        let bounds = match footprint {
            Footprint::Ellipse => [(0, view.width - 1), (0, view.height - 1)],
            Footprint::Tiles3dgs => {
                match tiles_3dgs([u, v], [mxx, mxy, myy], 0.3, [view.width, view.height]) {
                    Some(b) => b,
                    None => continue,
                }
            }
        };
        splats.push(Splat64 {
            index,
            z: p.z,
            u,
            v,
            conic: [c / det, -b / det, a / det],
            opacity,
            color: g.color,
            bounds,
        });
    }
    splats.sort_by_key(|s| ((s.z as f32).to_bits(), s.index));
    let pixels = (view.width * view.height) as usize;
    let mut out = Render64 {
        rgb: vec![0.0; 3 * pixels],
        alpha: vec![0.0; pixels],
        expected_depth: vec![0.0; pixels],
        pairs: 0xcbf2_9ce4_8422_2325,
    };
    let mut hash = |v: u64| {
        out.pairs = (out.pairs ^ v).wrapping_mul(0x100_0000_01b3);
    };
    for py in 0..view.height {
        for px in 0..view.width {
            let q = (py * view.width + px) as usize;
            let (x, y) = (f64::from(px) + 0.5, f64::from(py) + 0.5);
            let (mut t, mut rgb, mut depth) = (1.0f64, [0.0f64; 3], 0.0f64);
            for s in &splats {
                let [(x0, x1), (y0, y1)] = s.bounds;
                if px < x0 || px > x1 || py < y0 || py > y1 {
                    continue;
                }
                let (dx, dy) = (x - s.u, y - s.v);
                let d2 = s.conic[0] * dx * dx + 2.0 * s.conic[1] * dx * dy + s.conic[2] * dy * dy;
                if footprint == Footprint::Ellipse && d2 > 9.0 {
                    continue;
                }
                let raw = s.opacity * (-0.5 * d2).exp();
                let alpha = raw.min(0.99);
                if alpha < 1.0 / 255.0 {
                    continue;
                }
                if t * (1.0 - alpha) < f64::from(TRANSMITTANCE_MIN) {
                    hash(u64::MAX);
                    break;
                }
                hash(((q as u64) << 24) | ((s.index as u64) << 1) | u64::from(raw > 0.99));
                for (acc, c) in rgb.iter_mut().zip(s.color) {
                    *acc += c * alpha * t;
                }
                depth += s.z * alpha * t;
                t *= 1.0 - alpha;
            }
            for ((out, c), b) in out.rgb[3 * q..3 * q + 3]
                .iter_mut()
                .zip(rgb)
                .zip(background)
            {
                *out = c + t * b;
            }
            out.alpha[q] = 1.0 - t;
            out.expected_depth[q] = if t < 1.0 { depth / (1.0 - t) } else { 0.0 };
        }
    }
    out
}

/// The loss `Σ w·rgb + Σ wa·alpha + Σ we·expected depth` with fixed random weights.
struct Loss {
    rgb: Vec<f32>,
    alpha: Vec<f32>,
    expected_depth: Vec<f32>,
}

impl Loss {
    fn random(pixels: usize, seed: u64, depth_weight: f32) -> Self {
        let mut rng = SplitMix(seed);
        let mut draw = |n: usize, scale: f32| -> Vec<f32> {
            (0..n).map(|_| (rng.unit() * 2.0 - 1.0) * scale).collect()
        };
        Self {
            rgb: draw(3 * pixels, 1.0),
            alpha: draw(pixels, 0.5),
            expected_depth: draw(pixels, depth_weight),
        }
    }

    fn upstream(&self) -> RenderGradients<'_> {
        RenderGradients {
            rgb: &self.rgb,
            alpha: Some(&self.alpha),
            expected_depth: Some(&self.expected_depth),
        }
    }

    fn of(&self, r: &Render64) -> f64 {
        let dot =
            |w: &[f32], v: &[f64]| w.iter().zip(v).map(|(a, b)| f64::from(*a) * b).sum::<f64>();
        dot(&self.rgb, &r.rgb)
            + dot(&self.alpha, &r.alpha)
            + dot(&self.expected_depth, &r.expected_depth)
    }
}

// ---------------------------------------------------------------------------------------------
// Scenes.

/// A rotated, translated camera with fx ≠ fy and an off-centre principal point.
fn tilted_camera(width: u32, height: u32) -> Camera {
    let intrinsics = Intrinsics {
        fx: 0.9 * width as f32,
        fy: 0.85 * width as f32,
        cx: 0.52 * width as f32,
        cy: 0.47 * height as f32,
        width,
        height,
    };
    let rotation = Quat::from_rotation_y(0.15) * Quat::from_rotation_x(-0.1);
    let cam_to_world = Affine3A::from_rotation_translation(rotation, Vec3::new(0.1, -0.05, -0.2));
    Camera::from_camera_to_world(intrinsics, cam_to_world).unwrap()
}

/// `n` random Gaussians in front of `tilted_camera`: unnormalised rotations, opacities 0.2..0.97.
fn small_scene(n: usize, seed: u64, size: f32) -> GaussianSet {
    let mut rng = SplitMix(seed);
    let mut cols = (vec![], vec![], vec![], vec![], vec![]);
    for _ in 0..n {
        let z = 2.0 + 2.0 * rng.unit();
        cols.0.push([
            (rng.unit() - 0.5) * z * 0.8,
            (rng.unit() - 0.5) * z * 0.8,
            z,
        ]);
        cols.1.push([0, 1, 2].map(|_| size * (0.4 + rng.unit())));
        cols.2.push([0, 1, 2, 3].map(|_| rng.unit() * 2.0 - 1.0));
        cols.3.push(0.2 + 0.77 * rng.unit());
        cols.4.push([rng.unit(), rng.unit(), rng.unit()]);
    }
    GaussianSet::new(cols.0, cols.1, cols.2, cols.3, cols.4).unwrap()
}

fn options(footprint: Footprint) -> RenderOptions {
    RenderOptions {
        background: [0.2, 0.4, 0.6],
        footprint,
        features: false,
        ..RenderOptions::default()
    }
}

fn backward(set: &GaussianSet, camera: &Camera, opts: &RenderOptions, loss: &Loss) -> Gradients {
    let raster = CpuRasterizer::new();
    let (_, saved) = raster.render_saved(set, camera, opts).unwrap();
    raster
        .backward(&saved, &loss.upstream(), BackwardOptions { camera: true })
        .unwrap()
}

// ---------------------------------------------------------------------------------------------
// Finite differences.

/// Checks every Gaussian parameter and the camera's seven against central differences (step
/// 1e-6) of the f64 dense model; returns (checked, skipped) components.
///
/// Tolerance: `|rust − fd| ≤ 5e-4·scale + 1e-3·|fd|`, `scale` the largest |fd| of that kind of
/// parameter in the scene (position, log scale, …). The Rust pass composites in f32 (relative
/// rounding ~1e-7 a step, recovered transmittances ~1e-6) and sums up to a few thousand pixels;
/// the f64 differences are good to ~1e-8. Observed: at most 4e-5 of the scale (rotations), most
/// kinds under 1e-5; colours 1e-7.
fn check_against_finite_differences(
    set: &GaussianSet,
    camera: &Camera,
    footprint: Footprint,
    seed: u64,
) -> (usize, usize) {
    let opts = options(footprint);
    let (w, h) = (camera.width(), camera.height());
    let loss = Loss::random((w * h) as usize, seed, 0.1);
    let grads = backward(set, camera, &opts, &loss);
    let params = Params::from_set(set);
    let bg = opts.background.map(f64::from);
    let base_view = View64::new(camera, [0.0; 7]);

    // The dense model must render what the rasterizer renders (else the pairs differ).
    let image = CpuRasterizer::new().render(set, camera, &opts).unwrap();
    let base = render64(&params, &base_view, footprint, bg);
    let worst = image
        .rgb
        .iter()
        .zip(&base.rgb)
        .map(|(a, b)| (f64::from(*a) - b).abs())
        .fold(0.0, f64::max);
    assert!(
        worst < 1e-4,
        "the dense model renders {worst} away from the rasterizer"
    );

    let step = 1e-6;
    let (mut checked, mut skipped) = (0, 0);
    // 14 parameters of each Gaussian, grouped by kind for the scale.
    let kinds: [(&str, std::ops::Range<usize>); 5] = [
        ("position", 0..3),
        ("log scale", 3..6),
        ("rotation", 6..10),
        ("opacity logit", 10..11),
        ("colour", 11..14),
    ];
    for (name, range) in kinds {
        let mut rows = Vec::new();
        for i in 0..params.len() {
            for k in range.clone() {
                let mut plus = params.clone();
                plus[i].set(k, params[i].get(k) + step);
                let mut minus = params.clone();
                minus[i].set(k, params[i].get(k) - step);
                let rp = render64(&plus, &base_view, footprint, bg);
                let rm = render64(&minus, &base_view, footprint, bg);
                if rp.pairs != base.pairs || rm.pairs != base.pairs {
                    skipped += 1;
                    continue;
                }
                let fd = (loss.of(&rp) - loss.of(&rm)) / (2.0 * step);
                rows.push((i, k, fd, f64::from(grads.gaussians.row(i)[k])));
            }
        }
        let scale = rows.iter().map(|r| r.2.abs()).fold(1e-6, f64::max);
        let worst = rows
            .iter()
            .map(|r| (r.3 - r.2).abs() / scale)
            .fold(0.0, f64::max);
        eprintln!(
            "{footprint:?} {name}: {} checked, scale {scale:.3e}, worst error / scale {worst:.2e}",
            rows.len()
        );
        for (i, k, fd, got) in &rows {
            let tol = 5e-4 * scale + 1e-3 * fd.abs();
            assert!(
                (got - fd).abs() <= tol,
                "{footprint:?} Gaussian {i} {name}[{k}]: backward {got}, finite differences {fd} (scale {scale})"
            );
        }
        checked += rows.len();
    }
    // The camera.
    let mut rows = Vec::new();
    for k in 0..7 {
        let mut tp = [0.0; 7];
        tp[k] = step;
        let mut tm = [0.0; 7];
        tm[k] = -step;
        let rp = render64(&params, &View64::new(camera, tp), footprint, bg);
        let rm = render64(&params, &View64::new(camera, tm), footprint, bg);
        if rp.pairs != base.pairs || rm.pairs != base.pairs {
            skipped += 1;
            continue;
        }
        rows.push((
            k,
            (loss.of(&rp) - loss.of(&rm)) / (2.0 * step),
            grads.camera.tangent[k],
        ));
    }
    let scale = rows.iter().map(|r| r.1.abs()).fold(1e-6, f64::max);
    let worst = rows
        .iter()
        .map(|r| (r.2 - r.1).abs() / scale)
        .fold(0.0, f64::max);
    eprintln!(
        "{footprint:?} camera: {} checked, scale {scale:.3e}, worst error / scale {worst:.2e}, skipped so far {skipped}",
        rows.len()
    );
    for (k, fd, got) in &rows {
        assert!(
            (got - fd).abs() <= 2e-3 * scale + 1e-3 * fd.abs(),
            "{footprint:?} camera[{k}]: backward {got}, finite differences {fd}"
        );
    }
    checked += rows.len();
    (checked, skipped)
}

#[test]
fn gradients_match_finite_differences_of_a_float64_model_in_both_footprints() {
    let camera = tilted_camera(40, 32);
    for footprint in [Footprint::Ellipse, Footprint::Tiles3dgs] {
        for seed in [1, 2] {
            let set = small_scene(6, seed, 0.12);
            let (checked, skipped) =
                check_against_finite_differences(&set, &camera, footprint, seed);
            assert!(
                skipped * 20 <= checked,
                "{footprint:?} seed {seed}: {skipped} components crossed an edge, {checked} checked"
            );
        }
    }
}

#[test]
fn gradients_match_finite_differences_through_the_clamp_and_the_early_stop() {
    // A stack of nearly opaque Gaussians: the centre pixels reach the transmittance stop and the
    // front ones clamp alpha at 0.99.
    let camera = tilted_camera(32, 24);
    let mut set = small_scene(5, 7, 0.25);
    let positions: Vec<[f32; 3]> = (0..5)
        .map(|i| {
            let p = camera.camera_to_world().transform_point3(Vec3::new(
                0.02 * i as f32,
                -0.01 * i as f32,
                2.0 + 0.3 * i as f32,
            ));
            p.to_array()
        })
        .collect();
    set = GaussianSet::new(
        positions,
        set.scales().to_vec(),
        set.rotations().to_vec(),
        vec![0.995, 0.9, 0.97, 0.8, 0.99],
        set.colors().to_vec(),
    )
    .unwrap();
    let opts = options(Footprint::Ellipse);
    let image = CpuRasterizer::new().render(&set, &camera, &opts).unwrap();
    assert!(
        image.alpha.iter().any(|a| 1.0 - a < 1e-3),
        "the stack reaches the stop"
    );
    for footprint in [Footprint::Ellipse, Footprint::Tiles3dgs] {
        let (checked, skipped) = check_against_finite_differences(&set, &camera, footprint, 11);
        assert!(
            skipped * 20 <= checked,
            "{footprint:?}: {skipped} skipped, {checked} checked"
        );
    }
}

// ---------------------------------------------------------------------------------------------
// Properties.

fn saved_backward(
    raster: &CpuRasterizer,
    set: &GaussianSet,
    camera: &Camera,
    opts: &RenderOptions,
    upstream: &RenderGradients<'_>,
) -> Gradients {
    let (_, saved) = raster.render_saved(set, camera, opts).unwrap();
    raster
        .backward(&saved, upstream, BackwardOptions { camera: true })
        .unwrap()
}

#[test]
fn a_gaussian_that_reaches_no_pixel_gets_exactly_zero_gradient() {
    let camera = tilted_camera(40, 32);
    let base = small_scene(8, 3, 0.12);
    let to_world = |p: Vec3| camera.camera_to_world().transform_point3(p).to_array();
    // Behind the camera, behind the near plane, off to the side, beyond far, and opacity under
    // 1/255: each skipped or reaching no pixel.
    let hidden = [
        (to_world(Vec3::new(0.0, 0.0, -2.0)), 0.5),
        (to_world(Vec3::new(0.0, 0.0, 0.005)), 0.5),
        (to_world(Vec3::new(40.0, 0.0, 3.0)), 0.5),
        (to_world(Vec3::new(0.0, 0.0, 150.0)), 0.5),
        (to_world(Vec3::new(0.0, 0.0, 3.0)), 0.003),
    ];
    let mut cols = (
        base.positions().to_vec(),
        base.scales().to_vec(),
        base.rotations().to_vec(),
        base.opacities().to_vec(),
        base.colors().to_vec(),
    );
    for (p, o) in hidden {
        cols.0.push(p);
        cols.1.push([0.1; 3]);
        cols.2.push([1.0, 0.2, 0.0, 0.0]);
        cols.3.push(o);
        cols.4.push([0.5; 3]);
    }
    let set = GaussianSet::new(cols.0, cols.1, cols.2, cols.3, cols.4).unwrap();
    for footprint in [Footprint::Ellipse, Footprint::Tiles3dgs] {
        let loss = Loss::random(40 * 32, 5, 0.1);
        let g = saved_backward(
            &CpuRasterizer::new(),
            &set,
            &camera,
            &options(footprint),
            &loss.upstream(),
        );
        for i in 8..13 {
            assert_eq!(
                g.gaussians.row(i),
                [0.0; 14],
                "{footprint:?}: hidden Gaussian {i}"
            );
            assert_eq!(g.gaussians.means2d[i], [0.0; 2]);
        }
        assert!(
            (0..8).any(|i| g.gaussians.row(i) != [0.0; 14]),
            "the visible ones learn"
        );
    }
}

#[test]
fn scaling_the_loss_scales_the_gradient() {
    let camera = tilted_camera(40, 32);
    let set = small_scene(10, 4, 0.12);
    let loss = Loss::random(40 * 32, 9, 0.1);
    let doubled = Loss {
        rgb: loss.rgb.iter().map(|v| 2.0 * v).collect(),
        alpha: loss.alpha.iter().map(|v| 2.0 * v).collect(),
        expected_depth: loss.expected_depth.iter().map(|v| 2.0 * v).collect(),
    };
    let scaled = Loss {
        rgb: loss.rgb.iter().map(|v| 0.37 * v).collect(),
        alpha: loss.alpha.iter().map(|v| 0.37 * v).collect(),
        expected_depth: loss.expected_depth.iter().map(|v| 0.37 * v).collect(),
    };
    for footprint in [Footprint::Ellipse, Footprint::Tiles3dgs] {
        let raster = CpuRasterizer::new();
        let opts = options(footprint);
        let g1 = saved_backward(&raster, &set, &camera, &opts, &loss.upstream());
        let g2 = saved_backward(&raster, &set, &camera, &opts, &doubled.upstream());
        let g3 = saved_backward(&raster, &set, &camera, &opts, &scaled.upstream());
        for i in 0..set.len() {
            // The pass is linear in the upstream gradient, and doubling is exact in floating point.
            assert_eq!(g2.gaussians.row(i), g1.gaussians.row(i).map(|v| 2.0 * v));
            // Any other factor: within f32 rounding of the per-pixel products (1e-5 of the row's
            // largest entry).
            let (a, b) = (g1.gaussians.row(i), g3.gaussians.row(i));
            let big = a.iter().fold(0.0f32, |m, v| m.max(v.abs()));
            for k in 0..14 {
                assert!(
                    (b[k] - 0.37 * a[k]).abs() <= 1e-5 * big,
                    "{footprint:?} {i}[{k}]: {} vs {}",
                    b[k],
                    0.37 * a[k]
                );
            }
        }
        for k in 0..7 {
            assert_eq!(g2.camera.tangent[k], 2.0 * g1.camera.tangent[k]);
        }
    }
}

#[test]
fn the_colour_gradient_of_the_only_gaussian_at_a_pixel_is_its_blending_weight() {
    let camera = tilted_camera(40, 32);
    let set = small_scene(1, 12, 0.2);
    let raster = CpuRasterizer::new();
    for footprint in [Footprint::Ellipse, Footprint::Tiles3dgs] {
        let opts = options(footprint);
        let pixels: Vec<(u32, u32)> = (0..32).flat_map(|y| (0..40).map(move |x| (x, y))).collect();
        let weights = raster.pixel_weights(&set, &camera, &opts, &pixels).unwrap();
        let mut seen = 0;
        for (&(x, y), w) in pixels.iter().zip(&weights) {
            if w.is_empty() {
                continue;
            }
            seen += 1;
            for c in 0..3 {
                let mut rgb = vec![0.0f32; 3 * 40 * 32];
                rgb[3 * (y * 40 + x) as usize + c] = 1.0;
                let g = saved_backward(&raster, &set, &camera, &opts, &RenderGradients::rgb(&rgb));
                assert_eq!(
                    g.gaussians.colors[0][c], w[0].weight,
                    "{footprint:?} pixel ({x}, {y})"
                );
            }
            if seen > 12 {
                break;
            }
        }
        assert!(seen > 12, "the Gaussian covers pixels");
    }
}

#[test]
fn non_finite_inputs_are_refused_before_any_work() {
    let camera = tilted_camera(16, 16);
    let raster = CpuRasterizer::new();
    let opts = options(Footprint::Ellipse);
    let set = small_scene(3, 1, 0.1);
    for bad in [f32::NAN, f32::INFINITY, f32::NEG_INFINITY] {
        let mut positions = set.positions().to_vec();
        positions[1][2] = bad;
        let broken = GaussianSet::new(
            positions,
            set.scales().to_vec(),
            set.rotations().to_vec(),
            set.opacities().to_vec(),
            set.colors().to_vec(),
        )
        .unwrap();
        assert!(raster.render_saved(&broken, &camera, &opts).is_err());
        let mut opacities = set.opacities().to_vec();
        opacities[0] = bad;
        let broken = GaussianSet::new(
            set.positions().to_vec(),
            set.scales().to_vec(),
            set.rotations().to_vec(),
            opacities,
            set.colors().to_vec(),
        )
        .unwrap();
        assert!(raster.render_saved(&broken, &camera, &opts).is_err());
    }
    let (_, saved) = raster.render_saved(&set, &camera, &opts).unwrap();
    let mut rgb = vec![0.0f32; 3 * 256];
    rgb[7] = f32::NAN;
    assert!(
        raster
            .backward(
                &saved,
                &RenderGradients::rgb(&rgb),
                BackwardOptions::default()
            )
            .is_err()
    );
    rgb[7] = f32::INFINITY;
    assert!(
        raster
            .backward(
                &saved,
                &RenderGradients::rgb(&rgb),
                BackwardOptions::default()
            )
            .is_err()
    );
    let short = vec![0.0f32; 3 * 255];
    assert!(
        raster
            .backward(
                &saved,
                &RenderGradients::rgb(&short),
                BackwardOptions::default()
            )
            .is_err()
    );
    let rgb = vec![0.0f32; 3 * 256];
    let alpha = vec![f32::NAN; 256];
    let upstream = RenderGradients {
        rgb: &rgb,
        alpha: Some(&alpha),
        expected_depth: None,
    };
    assert!(
        raster
            .backward(&saved, &upstream, BackwardOptions::default())
            .is_err()
    );
}

#[test]
fn the_saved_forward_pass_renders_the_same_image_bit_for_bit() {
    let camera = tilted_camera(70, 50);
    let set = small_scene(200, 21, 0.08);
    let raster = CpuRasterizer::new();
    for footprint in [Footprint::Ellipse, Footprint::Tiles3dgs] {
        let opts = RenderOptions {
            footprint,
            ..RenderOptions::default()
        };
        let plain = raster.render(&set, &camera, &opts).unwrap();
        let (saved_image, _) = raster.render_saved(&set, &camera, &opts).unwrap();
        assert_eq!(plain, saved_image);
    }
}

#[test]
fn gradients_do_not_depend_on_threads_or_the_pair_budget() {
    let camera = tilted_camera(70, 50);
    let set = small_scene(300, 22, 0.08);
    let loss = Loss::random(70 * 50, 3, 0.1);
    for footprint in [Footprint::Ellipse, Footprint::Tiles3dgs] {
        let opts = options(footprint);
        let one = saved_backward(
            &CpuRasterizer::with_threads(1).unwrap(),
            &set,
            &camera,
            &opts,
            &loss.upstream(),
        );
        let three = saved_backward(
            &CpuRasterizer::with_threads(3).unwrap(),
            &set,
            &camera,
            &opts,
            &loss.upstream(),
        );
        let banded = saved_backward(
            &CpuRasterizer::new().with_pair_budget(64),
            &set,
            &camera,
            &opts,
            &loss.upstream(),
        );
        assert_eq!(one, three, "{footprint:?}: threads");
        assert_eq!(one, banded, "{footprint:?}: bands");
    }
}

#[test]
fn rotation_gradients_are_orthogonal_to_the_stored_quaternion_and_zero_scales_learn_nothing() {
    let camera = tilted_camera(40, 32);
    let set = small_scene(6, 31, 0.15);
    let mut scales = set.scales().to_vec();
    scales[2] = [0.0, 0.0, 0.0];
    scales[3] = [0.1, 0.0, 0.0];
    let set = GaussianSet::new(
        set.positions().to_vec(),
        scales,
        set.rotations().to_vec(),
        set.opacities().to_vec(),
        set.colors().to_vec(),
    )
    .unwrap();
    let loss = Loss::random(40 * 32, 4, 0.1);
    for footprint in [Footprint::Ellipse, Footprint::Tiles3dgs] {
        let g = saved_backward(
            &CpuRasterizer::new(),
            &set,
            &camera,
            &options(footprint),
            &loss.upstream(),
        );
        for i in 0..set.len() {
            let (q, gq) = (set.rotations()[i], g.gaussians.rotations[i]);
            let dot: f32 = q.iter().zip(gq).map(|(a, b)| a * b).sum();
            let size =
                gq.iter().map(|v| v.abs()).sum::<f32>() * q.iter().map(|v| v.abs()).sum::<f32>();
            assert!(
                dot.abs() <= 1e-5 * size.max(1e-12),
                "{footprint:?} {i}: q·∂L/∂q = {dot}"
            );
            assert!(g.gaussians.row(i).iter().all(|v| v.is_finite()));
        }
        assert_eq!(
            g.gaussians.log_scales[2], [0.0; 3],
            "a zero scale: s·∂L/∂s = 0"
        );
        assert_eq!(&g.gaussians.log_scales[3][1..], &[0.0, 0.0]);
        assert_ne!(
            g.gaussians.positions[2], [0.0; 3],
            "a pixel-sized blob still moves"
        );
    }
}

#[test]
fn without_the_camera_option_the_camera_gradient_is_zero_and_the_rest_the_same() {
    let camera = tilted_camera(40, 32);
    let set = small_scene(8, 41, 0.12);
    let loss = Loss::random(40 * 32, 2, 0.1);
    let raster = CpuRasterizer::new();
    let (_, saved) = raster
        .render_saved(&set, &camera, &options(Footprint::Ellipse))
        .unwrap();
    let with = raster
        .backward(&saved, &loss.upstream(), BackwardOptions { camera: true })
        .unwrap();
    let without = raster
        .backward(&saved, &loss.upstream(), BackwardOptions::default())
        .unwrap();
    assert_eq!(without.camera.tangent, [0.0; 7]);
    assert_ne!(with.camera.tangent, [0.0; 7]);
    assert_eq!(with.gaussians, without.gaussians);
}
