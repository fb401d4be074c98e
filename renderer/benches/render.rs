//! Render time of the rasterizers: 2K (one C4G timestamp), 100K and 1M random Gaussians at
//! 256², 512² and 1920×1080; the CPU rasterizer always, the wgpu one too with the `gpu` feature
//! (one run, so the two can be compared).
//!
//!     cargo bench -p c4g-renderer --bench render
//!     cargo bench -p c4g-renderer --features gpu --bench render
//!
//! The scene is plausible rather than adversarial: Gaussians fill a frustum slab at depth 2..6 in
//! front of a camera with C4G's default intrinsics, nearly all in view, anisotropic, randomly
//! rotated, opacity 0.1..1, with world sizes that project to σ ≈ 1.5 / 3 / 11 pixels at the three
//! resolutions. Results go in the issue notes with the machine line this prints.
#![allow(clippy::unwrap_used, clippy::expect_used, missing_docs)]

use std::time::Duration;

use c4g_renderer::{
    Camera, CpuRasterizer, GaussianSet, NormalizedIntrinsics, Rasterizer, RenderOptions,
};
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

fn bench(c: &mut Criterion, group_name: &str, rasterizer: &dyn Rasterizer) {
    let options = RenderOptions::default();
    let mut group = c.benchmark_group(group_name);
    for n in [2_000usize, 100_000, 1_000_000] {
        let set = scene(n);
        for (w, h) in [(256u32, 256u32), (512, 512), (1920, 1080)] {
            let camera = Camera::from_normalized(
                NormalizedIntrinsics::C4G_DEFAULT,
                w,
                h,
                Affine3A::IDENTITY,
            )
            .unwrap();
            group.throughput(Throughput::Elements(n as u64));
            group.bench_with_input(
                BenchmarkId::new(format!("{n}"), format!("{w}x{h}")),
                &(&set, &camera),
                |b, (set, camera)| b.iter(|| rasterizer.render(set, camera, &options).unwrap()),
            );
        }
    }
    group.finish();
}

fn render(c: &mut Criterion) {
    let cpu = CpuRasterizer::new();
    eprintln!(
        "machine: {}; CPU rasterizer threads: {}",
        machine(),
        cpu.threads()
    );
    bench(c, "cpu_render", &cpu);
    #[cfg(feature = "gpu")]
    match c4g_renderer::GpuRasterizer::new() {
        Ok(gpu) => {
            eprintln!("wgpu adapter: {}", gpu.adapter());
            bench(c, "gpu_render", &gpu);
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
