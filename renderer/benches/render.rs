//! Render time of the rasterizers: 2K (one C4G timestamp), 100K and 1M random Gaussians at
//! 256², 512² and 1920×1080, with each footprint (ids `<n>/<size>` for the ellipse,
//! `<n>_3dgs/<size>` for the 3DGS tiles); the CPU rasterizer always (group `cpu_render`), the wgpu
//! one too with the `gpu` feature (`gpu_render`; one run, so all can be compared).
//!
//!     cargo bench -p c4g-renderer --bench render
//!     cargo bench -p c4g-renderer --features gpu --bench render
//!     cargo bench -p c4g-renderer --features gpu --bench render -- 'render/2000(_3dgs)?/'
//!     C4G_BENCH_BEST_OF=5 cargo bench -p c4g-renderer --features gpu --bench render
//!
//! `C4G_BENCH_BEST_OF=N` prints the fastest of N renders per case instead, the two footprints
//! alternating: what compares them on a machine that other work shares, and then what a frame
//! costs with (almost) nothing to draw: 2K Gaussians all behind the camera (uploading, projecting
//! and sorting them, and the image's own allocation) and one small Gaussian in view (that, plus
//! reading the image's state back and finishing its pixels). `C4G_BENCH_ONLY=gpu` leaves the CPU
//! rasterizer out.
//!
//! The scene is plausible rather than adversarial: Gaussians fill a frustum slab at depth 2..6 in
//! front of a camera with C4G's default intrinsics, nearly all in view, anisotropic, randomly
//! rotated, opacity 0.1..1, with world sizes that project to σ ≈ 1.5 / 3 / 11 pixels at the three
//! resolutions. Results go in the issue notes with the machine line this prints.
#![allow(clippy::unwrap_used, clippy::expect_used, missing_docs)]

use std::time::Duration;

use c4g_renderer::{CpuRasterizer, Rasterizer, RenderOptions};
use c4g_scene::Footprint;
use c4g_scene::{Camera, GaussianSet, NormalizedIntrinsics};
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
    let mem_gib = std::fs::read_to_string("/proc/meminfo")
        .ok()
        .and_then(|s| {
            s.lines()
                .next()?
                .split_whitespace()
                .nth(1)?
                .parse::<f64>()
                .ok()
        })
        .map_or(0.0, |kib| kib / 1024.0 / 1024.0);
    let threads = std::thread::available_parallelism().map_or(0, usize::from);
    format!("{cpu}, {threads} threads, {mem_gib:.0} GiB")
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
    // Half-FOV tangent of C4G's default intrinsics: 0.5 / 0.8767.
    let tan = 0.5 / 0.8767;
    let (mut p, mut s, mut q, mut o, mut c) = (vec![], vec![], vec![], vec![], vec![]);
    for _ in 0..n {
        let z = 2.0 + 4.0 * rng.unit();
        p.push([
            (rng.unit() * 2.0 - 1.0) * tan * z,
            (rng.unit() * 2.0 - 1.0) * tan * z,
            z,
        ]);
        // 0.027 world units at depth 4 is σ ≈ 3 pixels at 512².
        s.push([0.0; 3].map(|_| 0.027 * (0.4 + 1.2 * rng.unit())));
        let r = [0.0; 4].map(|_| rng.unit() - 0.5);
        let norm = r.iter().map(|v| v * v).sum::<f32>().sqrt().max(1e-3);
        q.push(r.map(|v| v / norm));
        o.push(0.1 + 0.9 * rng.unit());
        c.push([rng.unit(), rng.unit(), rng.unit()]);
    }
    GaussianSet::new(p, s, q, o, c).unwrap()
}

/// Gaussians and image sizes of the cases.
const COUNTS: [usize; 3] = [2_000, 100_000, 1_000_000];
const SIZES: [(u32, u32); 3] = [(256, 256), (512, 512), (1920, 1080)];
/// The footprints, with the suffix of their benchmark ids.
const FOOTPRINTS: [(Footprint, &str); 2] =
    [(Footprint::Ellipse, ""), (Footprint::Tiles3dgs, "_3dgs")];

fn camera(w: u32, h: u32) -> Camera {
    Camera::from_normalized(NormalizedIntrinsics::C4G_DEFAULT, w, h, Affine3A::IDENTITY).unwrap()
}

fn options(footprint: Footprint) -> RenderOptions {
    RenderOptions {
        footprint,
        ..RenderOptions::default()
    }
}

fn bench(c: &mut Criterion, group_name: &str, rasterizer: &dyn Rasterizer) {
    let mut group = c.benchmark_group(group_name);
    for n in COUNTS {
        let set = scene(n);
        for (w, h) in SIZES {
            let camera = camera(w, h);
            // The footprints one after the other on each case, so that a busy machine weighs on
            // both alike.
            for (footprint, suffix) in FOOTPRINTS {
                let options = options(footprint);
                group.throughput(Throughput::Elements(n as u64));
                group.bench_with_input(
                    BenchmarkId::new(format!("{n}{suffix}"), format!("{w}x{h}")),
                    &(&set, &camera),
                    |b, (set, camera)| b.iter(|| rasterizer.render(set, camera, &options).unwrap()),
                );
            }
        }
    }
    group.finish();
}

/// With `C4G_BENCH_BEST_OF=N`, instead of criterion's statistics: the fastest of N renders of
/// every case, the footprints alternating render by render, as a table. On a machine other work
/// shares, a spike of load then costs one render, not the estimate.
fn best_of(name: &str, rasterizer: &dyn Rasterizer, reps: usize) {
    eprintln!("{name}: the fastest of {reps} renders, the footprints alternating");
    eprintln!("| Gaussians | size | ellipse | 3dgs | 3dgs / ellipse |");
    for n in COUNTS {
        let set = scene(n);
        for (w, h) in SIZES {
            let camera = camera(w, h);
            let mut best = [f64::INFINITY; 2];
            for _ in 0..reps {
                for (slot, (footprint, _)) in best.iter_mut().zip(FOOTPRINTS) {
                    let start = std::time::Instant::now();
                    std::hint::black_box(rasterizer.render(&set, &camera, &options(footprint)))
                        .unwrap();
                    *slot = slot.min(start.elapsed().as_secs_f64());
                }
            }
            eprintln!(
                "| {n} | {w}x{h} | {:.1} ms | {:.1} ms | {:.2} |",
                best[0] * 1e3,
                best[1] * 1e3,
                best[1] / best[0]
            );
        }
    }
    eprintln!("{name}: a frame's fixed cost, the fastest of {reps} renders (ellipse footprint)");
    eprintln!("| size | 2K behind the camera | one Gaussian in view |");
    let behind = {
        let set = scene(2_000);
        let flip = |p: &[f32; 3]| [p[0], p[1], -p[2]];
        let means: Vec<[f32; 3]> = set.positions().iter().map(flip).collect();
        GaussianSet::new(
            means,
            set.scales().to_vec(),
            set.rotations().to_vec(),
            set.opacities().to_vec(),
            set.colors().to_vec(),
        )
        .unwrap()
    };
    let one = GaussianSet::new(
        vec![[0.0, 0.0, 4.0]],
        vec![[0.01; 3]],
        vec![[1.0, 0.0, 0.0, 0.0]],
        vec![0.9],
        vec![[1.0, 0.5, 0.2]],
    )
    .unwrap();
    for (w, h) in SIZES {
        let camera = camera(w, h);
        let options = options(Footprint::Ellipse);
        let mut best = [f64::INFINITY; 2];
        for _ in 0..reps {
            for (slot, set) in best.iter_mut().zip([&behind, &one]) {
                let start = std::time::Instant::now();
                std::hint::black_box(rasterizer.render(set, &camera, &options)).unwrap();
                *slot = slot.min(start.elapsed().as_secs_f64());
            }
        }
        eprintln!(
            "| {w}x{h} | {:.2} ms | {:.2} ms |",
            best[0] * 1e3,
            best[1] * 1e3
        );
    }
}

fn render(c: &mut Criterion) {
    let cpu = CpuRasterizer::new();
    eprintln!(
        "machine: {}; CPU rasterizer threads: {}",
        machine(),
        cpu.threads()
    );
    let reps = std::env::var("C4G_BENCH_BEST_OF")
        .ok()
        .and_then(|v| v.parse::<usize>().ok())
        .filter(|&n| n > 0);
    let mut run = |name: &str, rasterizer: &dyn Rasterizer| match reps {
        Some(reps) => best_of(name, rasterizer, reps),
        None => bench(c, name, rasterizer),
    };
    // `C4G_BENCH_ONLY=gpu`: the wgpu rasterizer alone (scripts/device-check, where time is short).
    if std::env::var("C4G_BENCH_ONLY").as_deref() != Ok("gpu") {
        run("cpu_render", &cpu);
    }
    #[cfg(feature = "gpu")]
    match c4g_renderer::GpuRasterizer::new() {
        Ok(gpu) => {
            eprintln!("wgpu adapter: {}", gpu.adapter());
            run("gpu_render", &gpu);
        }
        Err(e) => eprintln!("gpu_render skipped: {e}"),
    }
}

criterion_group! {
    name = benches;
    config = Criterion::default()
        .sample_size(10)
        .warm_up_time(Duration::from_millis(500))
        .measurement_time(Duration::from_secs(3));
    targets = render
}
criterion_main!(benches);
