//! The CPU backward pass against the float64 autograd reference on every fixture scene, both
//! footprints: `models/fixtures/gradients/<scene>.safetensors` (made by
//! `python -m c4g.raster.grad_reference`, see that folder's README) holds the gradients of
//! `L = Σ w·rgb + Σ wa·alpha + Σ we·expected depth` for the weights of [`upstream_weights`],
//! with respect to every Gaussian with finite parameters and to the camera.
//!
//! Tolerance, per scene and kind of parameter (position, log scale, rotation, opacity logit,
//! colour, 2D centre, camera): `|rust − reference| ≤ 1e-3·scale + 1e-3·|reference|`, `scale` the
//! largest |reference| of that kind in the scene. The reference is exact to ~1e-12; the Rust pass
//! composites in f32, where each pixel's quantities carry relative rounding of ~1e-7 per step
//! and recovered transmittances ~1e-6, summed over up to 12K pixels per Gaussian, and its conic
//! is rounded to f32. The scenes keep every (pixel, Gaussian) pair clear of the model's cuts
//! (the scenes' README), so no pair is composited by one and not the other. Observed worst
//! errors (printed with `--nocapture`): 2.3e-4 of the scale (stack-3dgs, log scales: dozens of
//! layers down to the transmittance stop, each recovered by an f32 division), most under 2e-5.
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use c4g_renderer::{BackwardOptions, CpuRasterizer, DifferentiableRasterizer, RenderGradients};
use common::{SCENES, SCENES_3DGS, load_scene, workspace};
use safetensors::{Dtype, SafeTensors};

/// The fixtures' loss weights (`c4g.raster.grad_reference.upstream_weights`): plane `p` (rgb 0,
/// alpha 1, expected depth 2) weight `k` is `2·frac((k·0x9E3779B1 + seed + p) / 2³²) − 1`,
/// rounded to f32; expected depth's then times 0.1.
fn upstream_weights(pixels: usize, seed: u64) -> [Vec<f32>; 3] {
    let plane = |n: usize, p: u64| -> Vec<f32> {
        (0..n as u64)
            .map(|k| {
                let h = (k * 0x9E37_79B1 + seed + p) % (1 << 32);
                (2.0 * (h as f64 / 4_294_967_296.0) - 1.0) as f32
            })
            .collect()
    };
    let depth = plane(pixels, 2)
        .into_iter()
        .map(|v| (f64::from(v) * 0.1) as f32)
        .collect();
    [plane(3 * pixels, 0), plane(pixels, 1), depth]
}

fn tensor(st: &SafeTensors, key: &str) -> Vec<f64> {
    let t = st.tensor(key).unwrap_or_else(|e| panic!("{key}: {e}"));
    match t.dtype() {
        Dtype::F64 => t
            .data()
            .chunks_exact(8)
            .map(|b| f64::from_le_bytes(b.try_into().unwrap()))
            .collect(),
        Dtype::I32 => t
            .data()
            .chunks_exact(4)
            .map(|b| f64::from(i32::from_le_bytes(b.try_into().unwrap())))
            .collect(),
        other => panic!("{key}: unexpected dtype {other:?}"),
    }
}

/// Compares one kind of gradient; returns the worst error over the scale.
fn compare(scene: &str, name: &str, got: &[f64], want: &[f64]) -> f64 {
    assert_eq!(got.len(), want.len(), "{scene} {name}");
    let scale = want.iter().fold(1e-12f64, |m, v| m.max(v.abs()));
    let mut worst = 0.0f64;
    for (k, (g, w)) in got.iter().zip(want).enumerate() {
        let err = (g - w).abs();
        assert!(
            err <= 1e-3 * scale + 1e-3 * w.abs(),
            "{scene} {name}[{k}]: rust {g}, reference {w} (scale {scale})"
        );
        worst = worst.max(err / scale);
    }
    worst
}

#[test]
fn gradients_match_the_float64_reference_on_every_fixture_scene() {
    let raster = CpuRasterizer::new();
    for name in SCENES.iter().chain(&SCENES_3DGS) {
        let scene = load_scene(name);
        let path = workspace().join(format!("models/fixtures/gradients/{name}.safetensors"));
        let bytes = std::fs::read(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        let st = SafeTensors::deserialize(&bytes).unwrap();
        let kept: Vec<usize> = tensor(&st, "kept").iter().map(|&i| i as usize).collect();
        let mut keep = vec![false; scene.gaussians.len()];
        for &i in &kept {
            keep[i] = true;
        }
        let set = scene.gaussians.select(&keep).unwrap();
        let (w, h) = (scene.camera.width(), scene.camera.height());
        let [rgb, alpha, depth] = upstream_weights((w * h) as usize, 0);
        let upstream = RenderGradients {
            rgb: &rgb,
            alpha: Some(&alpha),
            expected_depth: Some(&depth),
        };
        let (_, saved) = raster
            .render_saved(&set, &scene.camera, &scene.options)
            .unwrap();
        let g = raster
            .backward(&saved, &upstream, BackwardOptions { camera: true })
            .unwrap();
        let flat = |rows: Vec<f32>| rows.into_iter().map(f64::from).collect::<Vec<_>>();
        let gg = &g.gaussians;
        let kinds = [
            ("positions", flat(gg.positions.concat())),
            ("log_scales", flat(gg.log_scales.concat())),
            ("rotations", flat(gg.rotations.concat())),
            ("opacity_logits", flat(gg.opacity_logits.clone())),
            ("colors", flat(gg.colors.concat())),
            ("means2d", flat(gg.means2d.concat())),
            ("camera", g.camera.tangent.to_vec()),
        ];
        let mut report = Vec::new();
        for (kind, got) in kinds {
            let worst = compare(name, kind, &got, &tensor(&st, kind));
            report.push(format!("{kind} {worst:.1e}"));
        }
        eprintln!("{name}: worst error / scale: {}", report.join(", "));
    }
}
