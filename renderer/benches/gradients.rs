//! Cost of the CPU rasterizer's backward pass: the forward render alone (group `grad_forward`)
//! and the forward pass that keeps state plus one backward pass (`grad_forward_backward`), at
//! 2K, 20K and 100K random Gaussians, 256² and 512², both footprints (ids `<n>/<size>` for the
//! ellipse, `<n>_3dgs/<size>` for the 3DGS tiles).
//!
//!     cargo bench -p c4g-renderer --bench gradients
//!     C4G_BENCH_BEST_OF=5 cargo bench -p c4g-renderer --bench gradients
//!
//! `C4G_BENCH_BEST_OF=N` prints a table instead: the fastest of N of each (forward and forward +
//! backward alternating), their ratio, and the peak resident memory of the forward + backward
//! (VmHWM after resetting it, so it includes the scene and the process's baseline); then, unless
//! `C4G_BENCH_TORCH=0`, the baseline a researcher would otherwise use, PyTorch autograd through a
//! dense implementation of the same forward model (`python -m c4g.raster.grad_reference --bench`,
//! float32, chunks of 2048 pixels, every Gaussian at every pixel) at 2K and 20K Gaussians at 256²,
//! on the same CPU in the same run (`C4G_PYTHON`: the interpreter, default `.venv/bin/python`).
//!
//! The scene is `render.rs`'s: a frustum slab at depth 2..6 before C4G's default intrinsics,
//! anisotropic, randomly rotated, opacity 0.1..1, σ ≈ 1.5 pixels at 256² and 3 at 512². The loss
//! gradient is a fixed pattern of ±1 (an L1 loss's).
#![allow(clippy::unwrap_used, clippy::expect_used, missing_docs)]

use std::path::PathBuf;
use std::time::Instant;

use c4g_renderer::{
    BackwardOptions, CpuRasterizer, DifferentiableRasterizer, Rasterizer, RenderGradients,
    RenderOptions,
};
use c4g_scene::{Camera, Footprint, GaussianSet, NormalizedIntrinsics};
use criterion::{BenchmarkId, Criterion, Throughput, criterion_group, criterion_main};
use glam::Affine3A;

fn machine() -> String {
    let cpu = std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("model name"))
                .and_then(|l| l.split(':').nth(1))
                .map(|s| s.trim().to_owned())
        })
        .unwrap_or_else(|| "unknown CPU".to_owned());
    let threads = std::thread::available_parallelism().map_or(0, usize::from);
    format!("{cpu}, {threads} threads")
}

/// SplitMix64 in [0, 1).
struct Rng(u64);

impl Rng {
    fn unit(&mut self) -> f32 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        ((z ^ (z >> 31)) >> 40) as f32 / (1u64 << 24) as f32
    }
}

fn scene(n: usize) -> GaussianSet {
    let mut rng = Rng(n as u64);
    let tan = 0.5 / 0.8767;
    let (mut p, mut s, mut q, mut o, mut c) = (vec![], vec![], vec![], vec![], vec![]);
    for _ in 0..n {
        let z = 2.0 + 4.0 * rng.unit();
        p.push([
            (rng.unit() * 2.0 - 1.0) * tan * z,
            (rng.unit() * 2.0 - 1.0) * tan * z,
            z,
        ]);
        s.push([0.0; 3].map(|_| 0.027 * (0.4 + 1.2 * rng.unit())));
        let r = [0.0; 4].map(|_| rng.unit() - 0.5);
        let norm = r.iter().map(|v| v * v).sum::<f32>().sqrt().max(1e-3);
        q.push(r.map(|v| v / norm));
        o.push(0.1 + 0.9 * rng.unit());
        c.push([rng.unit(), rng.unit(), rng.unit()]);
    }
    GaussianSet::new(p, s, q, o, c).unwrap()
}

const COUNTS: [usize; 3] = [2_000, 20_000, 100_000];
const SIZES: [u32; 2] = [256, 512];
const FOOTPRINTS: [(Footprint, &str); 2] =
    [(Footprint::Ellipse, ""), (Footprint::Tiles3dgs, "_3dgs")];

fn camera(size: u32) -> Camera {
    Camera::from_normalized(
        NormalizedIntrinsics::C4G_DEFAULT,
        size,
        size,
        Affine3A::IDENTITY,
    )
    .unwrap()
}

fn options(footprint: Footprint) -> RenderOptions {
    RenderOptions {
        footprint,
        features: false,
        ..RenderOptions::default()
    }
}

/// An L1 loss's gradient: ±1 in a fixed pattern.
fn upstream(size: u32) -> Vec<f32> {
    let mut rng = Rng(7);
    (0..3 * size * size)
        .map(|_| if rng.unit() < 0.5 { -1.0 } else { 1.0 })
        .collect()
}

fn forward_backward(
    raster: &CpuRasterizer,
    set: &GaussianSet,
    camera: &Camera,
    options: &RenderOptions,
    rgb: &[f32],
) {
    let (image, saved) = raster.render_saved(set, camera, options).unwrap();
    std::hint::black_box(image);
    let g = raster
        .backward(
            &saved,
            &RenderGradients::rgb(rgb),
            BackwardOptions::default(),
        )
        .unwrap();
    std::hint::black_box(g);
}

fn bench(c: &mut Criterion) {
    eprintln!("machine: {}", machine());
    if let Some(reps) = std::env::var("C4G_BENCH_BEST_OF")
        .ok()
        .and_then(|v| v.parse().ok())
    {
        best_of(reps);
        return;
    }
    let raster = CpuRasterizer::new();
    for (group_name, backward) in [("grad_forward", false), ("grad_forward_backward", true)] {
        let mut group = c.benchmark_group(group_name);
        group.sample_size(10);
        for n in COUNTS {
            let set = scene(n);
            for size in SIZES {
                let camera = camera(size);
                let rgb = upstream(size);
                for (footprint, suffix) in FOOTPRINTS {
                    let options = options(footprint);
                    group.throughput(Throughput::Elements(n as u64));
                    group.bench_function(
                        BenchmarkId::new(format!("{n}{suffix}"), format!("{size}x{size}")),
                        |b| {
                            b.iter(|| {
                                if backward {
                                    forward_backward(&raster, &set, &camera, &options, &rgb);
                                } else {
                                    std::hint::black_box(
                                        raster.render(&set, &camera, &options).unwrap(),
                                    );
                                }
                            })
                        },
                    );
                }
            }
        }
        group.finish();
    }
}

/// Peak resident memory (VmHWM) in MiB, after `reset` cleared it (Linux; 0 elsewhere).
fn peak_mib(reset: bool) -> f64 {
    if reset {
        let _ = std::fs::write("/proc/self/clear_refs", "5");
        return 0.0;
    }
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("VmHWM"))
                .and_then(|l| l.split_whitespace().nth(1))
                .and_then(|v| v.parse::<f64>().ok())
        })
        .map_or(0.0, |kib| kib / 1024.0)
}

fn best_of(reps: usize) {
    let raster = CpuRasterizer::new();
    eprintln!("the fastest of {reps}, forward and forward + backward alternating");
    eprintln!(
        "| Gaussians | size | footprint | forward | forward + backward | ratio | peak RSS (fwd+bwd) |"
    );
    eprintln!("|---|---|---|---|---|---|---|");
    for n in COUNTS {
        let set = scene(n);
        for size in SIZES {
            let camera = camera(size);
            let rgb = upstream(size);
            for (footprint, _) in FOOTPRINTS {
                let options = options(footprint);
                let (mut fwd, mut both) = (f64::INFINITY, f64::INFINITY);
                let mut peak = 0.0f64;
                for _ in 0..reps {
                    let start = Instant::now();
                    std::hint::black_box(raster.render(&set, &camera, &options).unwrap());
                    fwd = fwd.min(start.elapsed().as_secs_f64());
                    peak_mib(true);
                    let start = Instant::now();
                    forward_backward(&raster, &set, &camera, &options, &rgb);
                    both = both.min(start.elapsed().as_secs_f64());
                    peak = peak.max(peak_mib(false));
                }
                eprintln!(
                    "| {n} | {size}² | {footprint} | {:.2} ms | {:.2} ms | {:.2} | {peak:.0} MiB |",
                    fwd * 1e3,
                    both * 1e3,
                    both / fwd
                );
            }
        }
    }
    if std::env::var("C4G_BENCH_TORCH").as_deref() == Ok("0") {
        return;
    }
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..");
    let python = std::env::var_os("C4G_PYTHON")
        .map(PathBuf::from)
        .unwrap_or_else(|| root.join(".venv/bin/python"));
    eprintln!("PyTorch dense autograd baseline (float32, one forward + backward), ellipse");
    eprintln!("| Gaussians | size | PyTorch | this crate (fwd + bwd) | speed-up |");
    eprintln!("|---|---|---|---|---|");
    for n in [2_000usize, 20_000] {
        let size = 256;
        let out = std::process::Command::new(&python)
            .args(["-m", "c4g.raster.grad_reference", "--bench"])
            .args([n.to_string(), size.to_string()])
            .current_dir(root.join("models/python"))
            .output();
        let seconds = out.ok().and_then(|o| {
            String::from_utf8_lossy(&o.stdout)
                .split_whitespace()
                .nth(1)
                .and_then(|v| v.parse::<f64>().ok())
        });
        let Some(torch) = seconds else {
            eprintln!(
                "| {n} | {size}² | (PyTorch not available at {}) | | |",
                python.display()
            );
            continue;
        };
        let set = scene(n);
        let camera = camera(size);
        let rgb = upstream(size);
        let options = options(Footprint::Ellipse);
        let mut both = f64::INFINITY;
        for _ in 0..reps {
            let start = Instant::now();
            forward_backward(&raster, &set, &camera, &options, &rgb);
            both = both.min(start.elapsed().as_secs_f64());
        }
        eprintln!(
            "| {n} | {size}² | {:.2} s | {:.2} ms | {:.0}x |",
            torch,
            both * 1e3,
            torch / both
        );
    }
}

criterion_group!(benches, bench);
criterion_main!(benches);
