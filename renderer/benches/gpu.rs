//! Render time of the wgpu rasterizer: 2K (one C4G timestamp), 100K and 1M random Gaussians at
//! 256², 512² and 1920×1080, read back to host memory (the time a caller waits for an `Image`).
//!
//!     cargo bench -p c4g-renderer --features gpu --bench gpu
//!
//! The scene is the one of `benches/cpu.rs` (same distribution and seeds), so the two compare:
//! Gaussians fill a frustum slab at depth 2..6 in front of a camera with C4G's default intrinsics,
//! anisotropic, randomly rotated, opacity 0.1..1, σ ≈ 1.5 / 3 / 11 pixels at the three
//! resolutions. `C4G_WGPU_ADAPTER` picks the adapter (e.g. `lavapipe`); the adapter and machine
//! lines it prints go in the issue notes with the numbers.
#![allow(clippy::unwrap_used, clippy::expect_used, missing_docs)]

use std::time::Duration;

use c4g_renderer::{
    Camera, GaussianSet, GpuRasterizer, NormalizedIntrinsics, Rasterizer, RenderOptions,
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

/// SplitMix64 in [0, 1), as in `benches/cpu.rs`.
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

fn render(c: &mut Criterion) {
    let rasterizer = match GpuRasterizer::new() {
        Ok(rasterizer) => rasterizer,
        Err(e) => {
            eprintln!("skipped: {e}");
            return;
        }
    };
    eprintln!("adapter: {}", rasterizer.adapter());
    eprintln!("machine: {}", machine());
    let options = RenderOptions::default();
    let mut group = c.benchmark_group("gpu_render");
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

criterion_group! {
    name = benches;
    config = Criterion::default()
        .sample_size(10)
        .warm_up_time(Duration::from_millis(500))
        .measurement_time(Duration::from_secs(3));
    targets = render
}
criterion_main!(benches);
